"""Initial points for 3D Gaussians when a scene has no SfM points (e.g. transforms.json datasets).

Order of preference in `initial_points`: the scene's SfM points; points lifted from depth priors (or reference
depth) of the training views, coloured by their pixels; points triangulated from the training views' known
poses (when given a folder to cache them in); uniform random points inside the training frusta.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from warpgs.data.camera import optical_axes_focus
from warpgs.data.points import PointCloud
from warpgs.data.scene import Scene


def _backproject(cam, rows: np.ndarray, cols: np.ndarray, depth: np.ndarray) -> np.ndarray:
    x = (cols + 0.5 - cam.cx) / cam.fx * depth
    y = (rows + 0.5 - cam.cy) / cam.fy * depth
    cam_pts = np.stack([x, y, depth], -1)
    return (cam_pts - cam.viewmat[:3, 3]) @ cam.viewmat[:3, :3]


def points_from_depth(scene: Scene, n: int = 100_000, views: Optional[Sequence[int]] = None,
                      source: str = "prior", seed: int = 0, min_confidence: float = 0.0) -> PointCloud:
    """Lift `n` random valid pixels of the views' depth priors (source="prior") or reference depth
    (source="depth") into world points with their image colours. min_confidence: with priors that carry a
    confidence, only pixels at least that confident."""
    rng = np.random.default_rng(seed)
    views = list(scene.train if views is None else views)
    per_view = -(-n // max(len(views), 1))
    xyz, rgb = [], []
    for v in views:
        if source == "prior":
            got = scene.inv_depth_prior_np(v)
            if got is None:
                continue
            inv, valid = got
            valid = valid & (inv > 0)
            confidence = scene.prior_confidence_np(v) if min_confidence > 0 else None
            if confidence is not None:
                valid = valid & (confidence >= min_confidence)
            depth = np.where(valid, 1.0 / np.where(valid, inv, 1.0), 0.0)
        elif source == "depth":
            got = scene.depth_np(v)
            if got is None:
                continue
            depth, valid = got
            valid = valid & np.isfinite(depth)
        else:
            raise ValueError(f"source must be 'prior' or 'depth', got {source!r}")
        rows, cols = np.nonzero(valid)
        if len(rows) == 0:
            continue
        pick = rng.choice(len(rows), size=min(per_view, len(rows)), replace=False)
        r, c = rows[pick], cols[pick]
        xyz.append(_backproject(scene.cameras[v], r, c, depth[r, c].astype(np.float64)))
        rgb.append(scene.image_np(v)[0][r, c])
    if not xyz:
        raise ValueError(f"points_from_depth: no view has a valid {source} map")
    return PointCloud(np.concatenate(xyz)[:n], np.concatenate(rgb)[:n])


def random_points(scene: Scene, n: int = 100_000, near: Optional[float] = None, far: Optional[float] = None,
                  seed: int = 0) -> PointCloud:
    """Points spread through the training views' frusta, uniform in inverse depth between near and far
    (default: 0.25x and 2x the distance from the cameras to the point their optical axes pass closest to).
    Colours are random."""
    rng = np.random.default_rng(seed)
    views = list(scene.train or range(len(scene)))
    cams = [scene.cameras[v] for v in views]
    bounds = scene.metadata.get("near_far")  # LLFF scenes: per-view near/far depths of the SfM points
    if (near is None or far is None) and bounds is not None:
        bounds = np.asarray(bounds, dtype=np.float64)[views]
        near, far = near or float(bounds[:, 0].min()), far or float(bounds[:, 1].max())
    if near is None or far is None:
        dist = _distance_to_focus(cams)
        near, far = near or 0.25 * dist, far or 2.0 * dist
    if not 0 < near < far:
        raise ValueError(f"random_points: need 0 < near < far, got {near}, {far}")
    which = rng.integers(0, len(cams), n)
    xyz = np.empty((n, 3))
    for k, cam in enumerate(cams):
        sel = np.nonzero(which == k)[0]
        rows = rng.uniform(0, cam.height, len(sel)) - 0.5
        cols = rng.uniform(0, cam.width, len(sel)) - 0.5
        depth = 1.0 / rng.uniform(1.0 / far, 1.0 / near, len(sel))
        xyz[sel] = _backproject(cam, rows, cols, depth)
    return PointCloud(xyz, rng.uniform(0, 1, (n, 3)))


def _distance_to_focus(cams) -> float:
    """Median camera distance to the least-squares closest point of all optical axes."""
    focus = optical_axes_focus(cams, max_condition=1e6)
    if focus is None:  # parallel axes (a planar camera array): no focus point
        raise ValueError("random_points: the cameras' axes are parallel; pass near= and far=")
    return float(np.median([np.linalg.norm(c.center - focus) for c in cams]))


MIN_TRIANGULATED_POINTS = 100  # fewer than this (a textureless or badly posed scene): random points instead
# model.init=triangulate asks for these points and nothing else: a few dozen accurate ones seed densification well
# enough (3 views of LLFF's real room give 135, orchids 274; style-transferred copies of leaves, orchids and room gave
# 79-87 at 0.4 px), so only fewer than this is an error.
MIN_TRIANGULATED_POINTS_STRICT = 20


def triangulated_points(scene: Scene, cache_dir: Path, *, strict: bool = False, thin_ok: bool = False,
                        **kwargs) -> Optional[tuple[PointCloud, str]]:
    """(points, "triangulated (...)") from the training views' known poses (warpgs.data.sfm.triangulate), cached
    in cache_dir. When that fails or finds under MIN_TRIANGULATED_POINTS points: None after saying why on
    stderr. strict (the points were asked for): the error when it fails or finds under
    MIN_TRIANGULATED_POINTS_STRICT, unless thin_ok (other points join them: model.prior_points), which keeps any
    number, saying so in the description."""
    from warpgs.data.errors import SceneError
    from warpgs.data.sfm.triangulate import triangulate_scene

    least = MIN_TRIANGULATED_POINTS_STRICT if strict else MIN_TRIANGULATED_POINTS
    thin = ""
    try:
        tri = triangulate_scene(scene, cache_dir, **kwargs)
        if strict and thin_ok and len(tri.points) < least:
            thin = f"; under {least}: the prior's points carry the start"
        elif len(tri.points) < least:
            hint = "; model.init=auto starts from the depth prior or random points instead" if strict else ""
            raise SceneError(cache_dir, f"triangulation found only {len(tri.points)} points (fewer than {least})"
                             f"{hint}")
    except (SceneError, RuntimeError, ValueError) as exc:  # pycolmap raises RuntimeError/ValueError
        if strict:
            raise
        print(f"triangulate: {exc}; using random points", file=sys.stderr)
        return None
    return tri.points, f"triangulated ({len(tri.points)} points, {tri.mean_error:.2f} px{thin})"


def initial_points(scene: Scene, n: int = 100_000, seed: int = 0, triangulate_dir: Optional[Path] = None,
                   **triangulate_options) -> tuple[PointCloud, str]:
    """(points, where they came from): "sfm", "depth_prior", "triangulated (...)" (only with triangulate_dir, the
    folder that caches them; triangulate_options go to triangulate_from_poses, e.g. shared_dir) or "random"."""
    if scene.points is not None and len(scene.points) > 0:
        return scene.points, "sfm"
    if scene.has("depth_prior", scene.train):
        return points_from_depth(scene, n, source="prior", seed=seed), "depth_prior"
    if triangulate_dir is not None:
        got = triangulated_points(scene, Path(triangulate_dir), **triangulate_options)
        if got is not None:
            return got
    return random_points(scene, n, seed=seed), "random"
