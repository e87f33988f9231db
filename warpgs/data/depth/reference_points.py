"""Sparse reference depth for scoring depth priors on real captures: the SfM points of *all* views, each projected
only into the views whose COLMAP track saw it (so occluded points never score a foreground pixel).

A complete model (images.bin) says which image id is which view by name. LLFF releases often ship sparse/0 with
points3D.bin but no images.bin (fern does). Then the ids are taken as the sorted view order (id = row + 1, what
COLMAP's import of a sorted folder gives) only when that reproduces poses_bounds.npy: LLFF wrote each view's
near/far as the 0.1 / 99.9 percentiles of the camera z of exactly the points whose track holds that view.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from warpgs.data.errors import PathLike, SceneError, require_file

_BOUNDS_RTOL = 1e-4  # near/far agreement needed to accept the id = row + 1 mapping


@dataclass
class TrackedPoints:
    xyz: np.ndarray  # [N, 3] float64
    error: np.ndarray  # [N] mean reprojection error (pixels of the images SfM ran on)
    tracks: list  # N arrays of the COLMAP image ids observing each point (unique, sorted)


def read_points3d_tracks(path: PathLike) -> TrackedPoints:
    """points3D.bin -> positions, errors and tracks; a truncated or inconsistent file is a SceneError naming it."""
    from warpgs.data.formats.colmap_check import read_points3d

    path = require_file(path, "COLMAP points3D.bin")
    _, xyz, error, tracks = read_points3d(path)
    if not np.all(np.isfinite(xyz)):
        raise SceneError(path, "point positions must be finite")
    return TrackedPoints(xyz, error, [np.unique(t["image_id"].astype(np.int64)) for t in tracks])


def _ids_from_bounds(points: TrackedPoints, scene, model: Path) -> dict[int, int]:
    """{image id: view} as id = view + 1, checked against the LLFF near/far bounds (see the module doc)."""
    bounds = scene.metadata.get("near_far")
    if bounds is None:
        raise SceneError(model, "no images.bin to name the track ids, and no LLFF near/far bounds to check the "
                                "sorted-order guess against")
    bounds = np.asarray(bounds, dtype=np.float64)
    for v, cam in enumerate(scene.native_cameras):
        seen = np.array([v + 1 in t for t in points.tracks])
        if seen.sum() < 2:
            raise SceneError(model, f"track id {v + 1} (view {cam.name}) observes fewer than 2 points")
        z = cam.world_to_camera(points.xyz[seen])[:, 2]
        got = np.percentile(z, [0.1, 99.9])
        if not np.allclose(got, bounds[v], rtol=_BOUNDS_RTOL):
            raise SceneError(model, f"cannot tell which view track id {v + 1} is: as view {cam.name} its points' "
                                    f"near/far {got.round(3).tolist()} differ from poses_bounds "
                                    f"{bounds[v].round(3).tolist()}")
    return {v + 1: v for v in range(len(scene.native_cameras))}


def _ids_from_images(model: Path, scene) -> Optional[dict[int, int]]:
    from warpgs.data.formats import colmap

    if not any((model / f"images{ext}").is_file() for ext in (".bin", ".txt")):
        return None
    rec = colmap.read_model(model)
    row = {name: v for v, name in enumerate(scene.names)}
    return {iid: row[im.name] for iid, im in rec.images.items() if im.name in row}


def view_reference_points(scene, model_dir: Optional[PathLike] = None) -> tuple[TrackedPoints, list[np.ndarray]]:
    """(the model's points, per view the indices of the points its track says it saw). model_dir defaults to
    <scene root>/sparse/0."""
    model = Path(model_dir) if model_dir is not None else scene.root / "sparse" / "0"
    points = read_points3d_tracks(model / "points3D.bin")
    ids = _ids_from_images(model, scene) or _ids_from_bounds(points, scene, model)
    per_view = [[] for _ in range(len(scene))]
    for p, track in enumerate(points.tracks):
        for iid in track:
            v = ids.get(int(iid))
            if v is not None:
                per_view[v].append(p)
    return points, [np.asarray(s, dtype=np.int64) for s in per_view]


def reference_depth(camera, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pixel positions [M, 2], camera z [M]) of the points in front of `camera` that land inside its image."""
    pix, z = camera.project(xyz)
    inside = (z > 0) & (pix[:, 0] >= 0) & (pix[:, 0] < camera.width) & (pix[:, 1] >= 0) & (pix[:, 1] < camera.height)
    return pix[inside], z[inside]


def sparse_depth_map(camera, xyz: np.ndarray) -> np.ndarray:
    """[H, W] float32 camera depth of the points at the pixels they fall in (the nearest when several share one),
    0 elsewhere (unknown, as reference depth maps mark it)."""
    pix, z = reference_depth(camera, xyz)
    out = np.full((camera.height, camera.width), np.inf)
    np.minimum.at(out, (pix[:, 1].astype(np.int64), pix[:, 0].astype(np.int64)), z)
    return np.where(np.isfinite(out), out, 0.0).astype(np.float32)
