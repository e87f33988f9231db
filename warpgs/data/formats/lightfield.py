"""Light-field camera arrays: sub-aperture images of a k x k grid, and the sparse-view protocols on them.

A light-field folder is an images/ folder plus grid positions, from either
  lightfield.json  {"rows": R, "cols": C, "views": {"<image name>": [row, col], ...},
                    "baseline": [bx, by], "intrinsics": {"fx":..., "fy":..., "cx":..., "cy":...}}
  (fractional positions are off-grid views), or image names such as r2_c1.png / 02_01.png (row, col).
Poses come from, in order: a COLMAP model or transforms.json in the folder; a planar array built from
"intrinsics" and either "baseline" (centres on the grid, +col to the right, +row downwards) or "centres"
({"<image name>": [x, y]}, measured centres on the array's plane, +y downwards), parallel optical axes; otherwise SfM.
Rectified arrays (e.g. Stanford's archive: every view warped so that one plane has no parallax) also give
"reference_depth": that plane's depth; each view's principal point is then shifted so that it projects alike in all.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

from warpgs.data.camera import Camera, intrinsics_matrix
from warpgs.data.errors import MissingSceneFile, PathLike, SceneError, read_json
from warpgs.data.formats.image_io import image_size, list_images
from warpgs.data.scene import MapFormat, Scene
from warpgs.data.formats.view_files import discover_view_files, read_label_names, read_map_format

LIGHTFIELD_FILE = "lightfield.json"
_NAME_PATTERNS = (re.compile(r"r(\d+)_c(\d+)"), re.compile(r"^(\d+)_(\d+)$"))
PROTOCOLS = ("grid", "file", "all")


def _read_spec(root: Path) -> dict:
    path = root / LIGHTFIELD_FILE
    if not path.is_file():
        return {}
    spec = read_json(path)
    if "views" in spec and not isinstance(spec["views"], dict):
        raise SceneError(path, '"views" must map image names to [row, col]')
    return spec


def grid_positions(root: PathLike, names: Optional[list[str]] = None) -> dict[str, tuple[float, float]]:
    """(row, col) of every sub-aperture image: from lightfield.json, else parsed from the file names."""
    root = Path(root)
    spec = _read_spec(root)
    if "views" in spec:
        try:
            return {str(k): (float(v[0]), float(v[1])) for k, v in spec["views"].items()}
        except (TypeError, ValueError, IndexError) as exc:
            raise SceneError(root / LIGHTFIELD_FILE, "each view needs a [row, col] position") from exc
    names = names if names is not None else [p.name for p in list_images(root / "images")]
    out = {}
    for n in names:
        for pattern in _NAME_PATTERNS:
            m = pattern.search(Path(n).stem)
            if m:
                out[n] = (float(m.group(1)), float(m.group(2)))
                break
    return out


def grid_protocol_split(positions: dict, names: list[str], k: int = 3) -> tuple[list[int], list[int]]:
    """Sparse light-field protocol: the k x k sub-grid spread evenly over the array (all of it for a k x k
    array) trains; every other view (held-out array positions and off-grid views) tests."""
    on_grid = {n: p for n, p in positions.items() if float(p[0]).is_integer() and float(p[1]).is_integer()}
    if not on_grid:
        raise ValueError("no on-grid views")
    rows = sorted({int(p[0]) for p in on_grid.values()})
    cols = sorted({int(p[1]) for p in on_grid.values()})
    if len(rows) < k or len(cols) < k:
        raise ValueError(f"a {k}x{k} training grid needs at least {k} rows and columns, the array has "
                         f"{len(rows)}x{len(cols)}")
    pick_r = {rows[i] for i in np.round(np.linspace(0, len(rows) - 1, k)).astype(int)}
    pick_c = {cols[i] for i in np.round(np.linspace(0, len(cols) - 1, k)).astype(int)}
    train, test = [], []
    for i, n in enumerate(names):
        p = positions.get(n) or positions.get(Path(n).name)
        if p is None:
            continue  # views that are not part of the array are in neither split
        is_train = n in on_grid or Path(n).name in on_grid
        (train if is_train and int(p[0]) in pick_r and int(p[1]) in pick_c else test).append(i)
    if len(train) != k * k:
        raise ValueError(f"expected {k * k} training views on the grid, found {len(train)}")
    return train, test


def _array_centres(path: Path, spec: dict, positions: dict) -> dict[str, tuple[float, float]]:
    """Each view's centre on the array's plane: measured ("centres") or on the grid ("baseline")."""
    try:
        if "centres" in spec:
            centres = {str(n): (float(xy[0]), float(xy[1])) for n, xy in spec["centres"].items()}
        else:
            bx, by = (float(b) for b in spec["baseline"])
            centres = {n: (c * bx, r * by) for n, (r, c) in positions.items()}
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        raise SceneError(path, 'a planar array needs "baseline": [bx, by] or "centres": {name: [x, y]}') from exc
    missing = sorted(set(positions) - set(centres))
    if missing:
        raise SceneError(path, f'"centres" has no centre for {missing[0]} ({len(missing)} views missing)')
    return centres


def _planar_grid_scene(root: Path, spec: dict, positions: dict, downscale: int, undistort: bool) -> Scene:
    """Poses of a planar array: identical orientation, centres on the plane z = 0 (_array_centres); with
    "reference_depth" z0, rectified views: the principal point shifted by f * centre / z0, so points at depth z0
    land on the same pixel in every view."""
    path = root / LIGHTFIELD_FILE
    centres = _array_centres(path, spec, positions)
    try:
        intr = spec["intrinsics"]
        fx, fy, cx, cy = (float(intr[k]) for k in ("fx", "fy", "cx", "cy"))
        z0 = float(spec["reference_depth"]) if "reference_depth" in spec else None
    except (KeyError, TypeError, ValueError) as exc:
        raise SceneError(path, 'a planar array needs "intrinsics": {fx, fy, cx, cy} (and a number for '
                               '"reference_depth", if given)') from exc
    if z0 is not None and not (np.isfinite(z0) and z0 > 0):
        raise SceneError(path, f'"reference_depth" must be a positive depth, got {z0}')
    cameras = []
    for name in sorted(positions):
        x, y = centres[name]
        image = root / "images" / name
        w, h = image_size(image)
        shift = (0.0, 0.0) if z0 is None else (fx * x / z0, fy * y / z0)
        K = intrinsics_matrix(fx, fy, cx + shift[0], cy + shift[1])
        view = np.eye(4)
        view[:3, 3] = [-x, -y, 0.0]  # centre at (x, y, 0), axes aligned with the world
        cameras.append(Camera(K, view, w, h, name=name, image_path=image))
    names = [c.name for c in cameras]
    return Scene(cameras, discover_view_files(root, names, [c.image_path for c in cameras]), root=root,
                 label_names=read_label_names(root), depth_format=read_map_format(root, "depth", MapFormat("depth")),
                 prior_format=read_map_format(root, "depth_prior", MapFormat()), source="lightfield-grid",
                 downscale=downscale, undistort=undistort)


def load_lightfield(root: PathLike, *, protocol: str = "grid", k: int = 3, downscale: int = 1, undistort: bool = True,
                    run_sfm_if_needed: bool = True, validate: bool = True) -> Scene:
    """A light-field folder -> Scene split by `protocol`: "grid" (k x k grid trains, the rest tests),
    "file" (split.json) or "all". Grid positions are kept in scene.metadata["grid_positions"]."""
    from warpgs.data.formats import colmap  # the pose sources
    from warpgs.data.formats import transforms

    root = Path(root)
    if not (root / "images").is_dir():
        raise MissingSceneFile(root / "images", "image folder")
    if protocol not in PROTOCOLS:
        raise ValueError(f"protocol must be one of {PROTOCOLS}, got {protocol!r}")
    spec = _read_spec(root)
    positions = grid_positions(root)
    if not positions:
        raise SceneError(root, f"no grid positions: add {LIGHTFIELD_FILE} or name images like r0_c0.png")
    missing = [n for n in positions if not (root / "images" / n).is_file()]
    if missing:
        raise MissingSceneFile(root / "images" / missing[0], f"sub-aperture image (listed in {LIGHTFIELD_FILE})")
    common = dict(downscale=downscale, undistort=undistort)
    split = "file" if protocol == "file" else "all"
    if colmap.find_model(root) is not None:
        scene = colmap.load_colmap(root, split=split, validate=False, **common)
    elif transforms.find_transforms(root):
        scene = transforms.load_transforms(root, split=split, validate=False, **common)
    elif "baseline" in spec or "centres" in spec:
        scene = _planar_grid_scene(root, spec, positions, **common)
    elif run_sfm_if_needed:
        from warpgs.data.sfm.run import run_sfm

        run_sfm(root / "images", root, image_names=sorted(positions))
        scene = colmap.load_colmap(root, split=split, validate=False, **common)
    else:
        raise SceneError(root, "no poses: add a COLMAP model, transforms.json or baseline (or centres) + intrinsics, "
                               "or allow SfM")
    if protocol == "grid":
        try:
            scene = scene.with_split(*grid_protocol_split(positions, scene.names, k))
        except ValueError as exc:
            raise SceneError(root / LIGHTFIELD_FILE if spec else root, str(exc)) from exc
    scene.source = "lightfield"
    scene.metadata["grid_positions"] = {n: positions.get(n, positions.get(Path(n).name)) for n in scene.names}
    return scene.validate() if validate else scene


def pseudo_video_order(positions: dict[str, tuple[float, float]], names: list[str]) -> list[int]:
    """Serpentine (boustrophedon) scan of the grid, so consecutive frames of the pseudo-video are neighbours:
    row 0 left to right, row 1 right to left, ... Views without a position go last, in name order."""
    placed = [(positions[n], i) for i, n in enumerate(names) if n in positions]
    placed.sort(key=lambda e: (e[0][0], e[0][1] if int(e[0][0]) % 2 == 0 else -e[0][1]))
    rest = [i for i, n in enumerate(names) if n not in positions]
    return [i for _, i in placed] + rest
