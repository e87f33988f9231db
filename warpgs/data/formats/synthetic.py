"""The built-in synthetic scene: a textured ground with coloured spheres and boxes, ray traced exactly.

`make_synthetic_scene(out_dir, kind)` writes a scene folder our loaders read:
    images/<name>.png         anti-aliased renders
    sparse/0/*.txt            COLMAP model: exact cameras + SfM-like points sampled on the true surfaces
    depth/<stem>.exr          exact camera-z depth at pixel centres (+inf for sky)
    normals/<stem>.exr        world-space unit normals
    labels/<stem>.png         object ids (0 = sky/unlabelled), names in labels.json
    split.json                train/test image names
    lightfield.json           (kind="lightfield") grid position of every view
    synthetic.json            generator settings; written last, so its presence means the folder is complete
kind="lightfield": a 3x3 camera array (parallel optical axes) for training plus off-grid views for testing.
kind="orbit": a dense ring of inward-looking views at alternating heights, LLFF split (every 8th is test).
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from warpgs.data.formats import raytrace

from warpgs.data.formats import textures
from warpgs.data.cache import cache_dir, touch
from warpgs.data.camera import Camera, intrinsics_matrix, look_at
from warpgs.data.formats.colmap import save_colmap
from warpgs.data.depth.files import write_exr, write_exr_channels
from warpgs.data.formats.image_io import write_png
from warpgs.data.points import PointCloud
from warpgs.data.formats.splits import llff_split, write_split_file

# Part of the cache folder's name: bump it when what a scene holds changes, so cached copies are made again.
# 2: the light field's plane-sweep priors carry a confidence channel (the issue-15 estimator).
GENERATOR_VERSION = 2
KINDS = ("lightfield", "orbit")
TARGET = np.array([0.0, 0.0, 0.35])  # where the cameras look


def scene_definition() -> raytrace.SceneDef:
    return raytrace.SceneDef(objects=[
        raytrace.Plane("ground", 0.0, 4.0, textures.checker_ground()),
        raytrace.Sphere("red sphere", (-0.55, 0.0, 0.5), 0.5,
                        textures.striped((0.85, 0.12, 0.10), (0.55, 0.05, 0.08), 3.0, axis=2, seed=11)),
        raytrace.Sphere("green sphere", (0.8, 0.6, 0.35), 0.35,
                        textures.mottled((0.15, 0.65, 0.20), (0.55, 0.85, 0.30), seed=12)),
        raytrace.Box("blue box", (0.6, -0.55, 0.3), (0.3, 0.3, 0.3), np.radians(25),
                     textures.mottled((0.12, 0.22, 0.80), (0.45, 0.60, 0.95), frequency=6.0, seed=13)),
        raytrace.Box("yellow box", (-0.15, 0.95, 0.45), (0.22, 0.22, 0.45), np.radians(-20),
                     textures.striped((0.90, 0.80, 0.15), (0.70, 0.45, 0.05), 4.0, axis=2, seed=14)),
        raytrace.Sphere("purple sphere", (-0.2, -0.95, 0.22), 0.22,
                        textures.mottled((0.50, 0.20, 0.65), (0.85, 0.55, 0.90), frequency=8.0, seed=15)),
    ])


@dataclass
class RigSettings:
    width: int = 128
    height: int = 96
    fov_x_deg: float = 60.0
    distance: float = 4.2  # from TARGET to the centre camera
    elevation_deg: float = 30.0
    grid: int = 3  # light field: grid x grid array
    baseline: float = 0.3  # light field: spacing of adjacent sub-apertures (scene units)
    n_orbit: int = 36


def _intrinsics(s: RigSettings) -> np.ndarray:
    f = 0.5 * s.width / np.tan(np.radians(s.fov_x_deg) / 2)
    return intrinsics_matrix(f, f, s.width / 2, s.height / 2)


def _eye(azimuth_deg: float, elevation_deg: float, distance: float) -> np.ndarray:
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return TARGET + distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def lightfield_rig(s: RigSettings) -> tuple[list[Camera], dict, list[int], list[int]]:
    """Grid cameras share the centre camera's orientation and sit on its image plane's axes, `baseline` apart;
    off-grid test views sit halfway between grid positions. Returns cameras, positions, train, test."""
    K = _intrinsics(s)
    centre = look_at(_eye(-90.0, s.elevation_deg, s.distance), TARGET)
    right, down = centre[0, :3], centre[1, :3]
    c0 = -centre[:3, :3].T @ centre[:3, 3]
    mid = (s.grid - 1) / 2
    grid_pos = [(float(r), float(c)) for r in range(s.grid) for c in range(s.grid)]
    off_pos = [(r + 0.5, c + 0.5) for r in (0.0, s.grid - 2.0) for c in (0.0, s.grid - 2.0)] if s.grid > 1 else []
    cameras, positions = [], {}
    for k, (r, c) in enumerate(grid_pos + off_pos):
        eye = c0 + (c - mid) * s.baseline * right + (r - mid) * s.baseline * down
        view = centre.copy()
        view[:3, 3] = -view[:3, :3] @ eye
        name = f"r{int(r)}_c{int(c)}.png" if k < len(grid_pos) else f"off_{k - len(grid_pos):02d}.png"
        cameras.append(Camera(K, view, s.width, s.height, name=name))
        positions[name] = [r, c]
    return cameras, positions, list(range(len(grid_pos))), list(range(len(grid_pos), len(cameras)))


def orbit_rig(s: RigSettings) -> tuple[list[Camera], list[int], list[int]]:
    K = _intrinsics(s)
    cameras = []
    for k in range(s.n_orbit):
        elevation = s.elevation_deg + (5.0 if k % 2 else -5.0)
        eye = _eye(-90.0 + 360.0 * k / s.n_orbit, elevation, s.distance)
        cameras.append(Camera(K, look_at(eye, TARGET), s.width, s.height, name=f"orbit_{k:03d}.png"))
    train, test = llff_split(len(cameras))
    return cameras, train, test


def sample_surface_points(renders: list, cameras: list, train: list[int], n_points: int,
                          rng: np.random.Generator) -> PointCloud:
    """SfM-like points: pixel-centre surface hits of the training views, with their colours, and for every view
    the points it actually sees (in the image, and its exact depth there agrees within 1%)."""
    per_view = -(-n_points // len(train))
    xyz, rgb = [], []
    for i in train:
        depth, cam = renders[i].depth, cameras[i]
        rows, cols = np.nonzero(np.isfinite(depth))
        pick = rng.choice(len(rows), size=min(per_view, len(rows)), replace=False)
        r, c = rows[pick], cols[pick]
        z = depth[r, c].astype(np.float64)
        cam_pts = np.stack([(c + 0.5 - cam.cx) / cam.fx * z, (r + 0.5 - cam.cy) / cam.fy * z, z], -1)
        xyz.append((cam_pts - cam.viewmat[:3, 3]) @ cam.viewmat[:3, :3])
        rgb.append(renders[i].rgb[r, c])  # the colour SfM would triangulate
    xyz, rgb = np.concatenate(xyz)[:n_points], np.concatenate(rgb)[:n_points]
    observed = []
    for i, cam in enumerate(cameras):
        if i not in train:
            observed.append(np.zeros(0, dtype=np.int64))
            continue
        pix, z = cam.project(xyz)
        col, row = np.floor(pix[:, 0]), np.floor(pix[:, 1])
        inside = (z > 0) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        idx = np.nonzero(inside)[0]
        seen = renders[i].depth[row[idx].astype(int), col[idx].astype(int)]
        observed.append(idx[np.abs(seen - z[idx]) < 0.01 * z[idx]])
    return PointCloud(xyz, rgb, observed)


def render_views(definition: raytrace.SceneDef, cameras: list[Camera], max_workers: int = 8) -> list:
    """Ray trace every view, several at once: numpy releases the GIL in its array loops, so threads scale
    (1.7x on 2 cores) without pickling the textures' closures. A 1280x800 orbit took 6+ minutes one view at a
    time. At most max_workers views are in flight, each holding about 1 GB of rays at a megapixel."""
    workers = max(1, min(len(cameras), os.cpu_count() or 1, max_workers))
    if workers == 1:
        return [raytrace.render(definition, cam) for cam in cameras]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(lambda cam: raytrace.render(definition, cam), cameras))


def _write_view(root: Path, cam: Camera, rend: raytrace.Rendering):
    stem = Path(cam.name).stem
    write_png(root / "images" / cam.name, rend.rgb)
    write_exr(root / "depth" / f"{stem}.exr", rend.depth, "depth")
    write_exr_channels(root / "normals" / f"{stem}.exr", {"N": rend.normal})
    write_png(root / "labels" / f"{stem}.png", rend.labels.astype(np.uint8))


def write_synthetic_scene(out_dir: Path, kind: str = "lightfield", settings: Optional[RigSettings] = None,
                          n_points: int = 3000, seed: int = 0, depth_priors: bool = False) -> Path:
    """Render and write the scene folder (see module docstring); returns out_dir.

    depth_priors=True also estimates inverse-depth priors for the training views with the built-in plane-sweep
    stereo (aligned to the points) into depth_priors/, as the sparse-view method expects.
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    s = settings or RigSettings()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    definition = scene_definition()
    if kind == "lightfield":
        cameras, positions, train, test = lightfield_rig(s)
    else:
        (cameras, train, test), positions = orbit_rig(s), None
    renders = render_views(definition, cameras)
    for cam, rend in zip(cameras, renders):
        _write_view(out_dir, cam, rend)
    points = sample_surface_points(renders, cameras, train, n_points, np.random.default_rng(seed))
    save_colmap(cameras, out_dir / "sparse" / "0", points)
    names = [c.name for c in cameras]
    write_split_file(out_dir / "split.json", names, train, test)
    (out_dir / "labels.json").write_text(json.dumps({str(k): v for k, v in definition.label_names.items()}, indent=1))
    if positions is not None:
        (out_dir / "lightfield.json").write_text(json.dumps(
            {"rows": s.grid, "cols": s.grid, "baseline": [s.baseline, s.baseline], "views": positions}, indent=1))
    if depth_priors:
        from warpgs.data.depth.priors import compute_depth_priors
        from warpgs.data.formats.load import load_scene

        compute_depth_priors(load_scene(out_dir, validate=False))
    meta = {"generator": "warpgs.data.formats.synthetic", "version": GENERATOR_VERSION, "kind": kind,
            "settings": asdict(s), "n_points": len(points), "seed": seed, "depth_priors": depth_priors,
            "seconds": round(time.perf_counter() - start, 3)}
    (out_dir / "synthetic.json").write_text(json.dumps(meta, indent=1))
    return out_dir


def make_synthetic_scene(out_dir, kind: str = "lightfield", width: int = 128, height: int = 96, *,
                         n_points: int = 3000, seed: int = 0, depth_priors: bool = False, **rig):
    """Write the synthetic scene into out_dir and return it loaded (a warpgs.data.Scene).

    Extra keyword arguments go to RigSettings (fov_x_deg, distance, elevation_deg, grid, baseline, n_orbit).
    """
    from warpgs.data.formats.load import load_scene

    write_synthetic_scene(Path(out_dir), kind, RigSettings(width=width, height=height, **rig), n_points, seed,
                          depth_priors)
    return load_scene(out_dir)


def default_scene(kind: str = "lightfield", width: int = 128, height: int = 96) -> Path:
    """Path of the cached synthetic scene (generated on first use under <cache>/synthetic/); the light field
    comes with plane-sweep depth priors for its training views. Safe to call from several processes at once:
    each renders into a private folder and the first to finish publishes it."""
    target = cache_dir() / "synthetic" / f"{kind}_{width}x{height}_v{GENERATOR_VERSION}"
    if (target / "synthetic.json").is_file():
        touch(target)  # used now (warpgs-cache drops the least recently used entries first)
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    tmp.chmod(0o755)  # mkdtemp makes it private; the published cache is for every user of the machine
    try:
        write_synthetic_scene(tmp, kind, RigSettings(width=width, height=height), depth_priors=(kind == "lightfield"))
        try:
            os.replace(tmp, target)  # atomic publish; fails if another process won the race
        except OSError:
            if not (target / "synthetic.json").is_file():
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return target
