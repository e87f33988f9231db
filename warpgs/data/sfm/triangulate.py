"""Sparse points from known poses: SIFT features, matching and pycolmap's triangulation with every pose and
intrinsic held fixed. For scenes that come with cameras but no points (transforms.json, LLFF, COLMAP models
without points3D), so that training can start from real surface points instead of random ones.

Only the views given (the training views by default: held-out views must not shape the model) are used.
The result is cached in `out_dir` (points.npz + triangulation.json) and, with `shared_dir`, also in a folder of
shared_dir named by the cache key, which every later run on the same capture reads instead of triangulating again
(the trainer passes $WARPGS_CACHE/triangulation: on the 2-core CPU triangulating phone64's 56 views took 47.7 s of
a 57.2 s start-up). The key covers the image files (path, size, modification time), the cameras, the views' places in the
scene and the settings, so changed images, poses or splits triangulate again.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from warpgs.data.cache import touch
from warpgs.data.errors import PathLike, SceneError
from warpgs.data.points import PointCloud
from warpgs.data.sfm import features
from warpgs.data.sfm.pairs import pose_similarity
from warpgs.utils.progress import Stages

CACHE_VERSION = 3  # 2: the same points on every run (seeded RANSAC, images numbered by name order); 3: view ids
POINTS_FILE = "points.npz"
INFO_FILE = "triangulation.json"
KEEP_TWO_VIEW_TRACKS_UP_TO = 4  # views; with so few, most points are seen twice only
# COLMAP's RANSAC (pair verification, point triangulation) draws a random seed unless given one: four processes
# triangulating one capture found 13,234-13,347 points. With this seed, _number_images_in_order and matching on one
# thread (deterministic=True) every run with the same inputs finds the same points.
RANDOM_SEED = 0
# COLMAP's CPU matcher searches an approximate (IVF) descriptor index; with several matching threads a pair's matches
# differ now and then between runs (2 of 25 runs of the 36-view orbit test scene). One thread: 0 of 25 differed;
# matching takes 1.8x as long on 2 cores (10 fern views: 7.2 s against 4.1). The brute-force matcher is exact but was
# 78x slower (313 s), so it is not the way.


@dataclass
class Triangulation:
    points: PointCloud  # observed_by indexes the scene's views (views not used observe nothing)
    mean_error: float  # mean reprojection error in pixels of the native images
    seconds: float  # time it took (the original run's, for a cached result)
    cached: bool
    info: dict


def _image_root(paths: Sequence[Path]) -> tuple[Path, list[str]]:
    resolved = [Path(p).resolve() for p in paths]
    root = Path(os.path.commonpath([str(p.parent) for p in resolved]))
    return root, [p.relative_to(root).as_posix() for p in resolved]


def cache_key(cameras, paths: Sequence[Path], settings: dict) -> str:
    """Changes when any image file is replaced or edited, any camera changes, or the settings change."""
    h = hashlib.sha1(json.dumps({"version": CACHE_VERSION, **settings}, sort_keys=True).encode())
    for cam, path in zip(cameras, paths):
        stat = Path(path).stat()
        h.update(f"{Path(path).resolve()}|{stat.st_size}|{stat.st_mtime_ns}|{cam.width}x{cam.height}|{cam.model}|"
                 f"{cam.distortion}".encode())
        h.update(np.ascontiguousarray(cam.K, np.float64).tobytes())
        h.update(np.ascontiguousarray(cam.viewmat, np.float64).tobytes())
    return h.hexdigest()[:24]


def _load_cached(out_dir: Path, key: str, n_views: int) -> Optional[Triangulation]:
    info_path, points_path = out_dir / INFO_FILE, out_dir / POINTS_FILE
    if not (info_path.is_file() and points_path.is_file()):
        return None
    try:
        info = json.loads(info_path.read_text())
        data = np.load(points_path, allow_pickle=False)
        if info.get("key") != key or str(data["key"]) != key:
            return None
        offsets, flat = data["obs_offsets"], data["obs_flat"]
        observed = [flat[offsets[i]:offsets[i + 1]] for i in range(n_views)]
        points = PointCloud(data["xyz"], data["rgb"], observed)
    except (OSError, ValueError, KeyError, json.JSONDecodeError):
        return None  # unreadable cache: triangulate again
    return Triangulation(points, float(info["mean_error"]), float(info["seconds"]), True, info)


def _save(out_dir: Path, key: str, tri: Triangulation) -> None:
    observed = tri.points.observed_by
    offsets = np.concatenate([[0], np.cumsum([len(o) for o in observed])]).astype(np.int64)
    flat = np.concatenate(observed).astype(np.int64) if observed else np.zeros(0, np.int64)
    out_dir.mkdir(parents=True, exist_ok=True)
    info_tmp = out_dir / f".{INFO_FILE}.{os.getpid()}.tmp"  # runs sharing a cache may write the same entry at once
    info_tmp.write_text(json.dumps({**tri.info, "key": key}, indent=1))
    os.replace(info_tmp, out_dir / INFO_FILE)
    tmp = out_dir / f".{POINTS_FILE}.{os.getpid()}.tmp.npz"
    np.savez(tmp, key=np.array(key), xyz=tri.points.xyz, rgb=tri.points.rgb, obs_offsets=offsets, obs_flat=flat)
    os.replace(tmp, out_dir / POINTS_FILE)  # last: its presence with the right key means the entry is complete


def _set_known_cameras(database: Path, names: list[str], cameras) -> dict:
    """Give every database image our intrinsics (flagged as known, so verification is calibrated); returns
    {database image name: image id}."""
    import pycolmap

    by_name = dict(zip(names, cameras))
    with pycolmap.Database.open(str(database)) as db:
        images = {im.name: im for im in db.read_all_images()}
        missing = sorted(set(names) - set(images))
        if missing:
            raise SceneError(None, f"triangulation: feature extraction skipped {missing[:3]} (unreadable images?)")
        for name, im in images.items():
            cam = by_name[name].to_pycolmap(im.camera_id)
            cam.has_prior_focal_length = True
            stored = db.read_camera(im.camera_id)
            if (stored.width, stored.height) != (cam.width, cam.height):
                raise SceneError(None, f"triangulation: image {name} is {stored.width}x{stored.height} but its camera "
                                       f"says {cam.width}x{cam.height}")
            db.update_camera(cam)
    return {n: images[n].image_id for n in names}


def _number_images_in_order(database: Path, names: list[str]) -> None:
    """Image (and frame) ids 1..n in the order of `names`. Feature extraction on several threads numbers images
    as their features are done, a different order each run, and the ids order pair verification and
    triangulation, so the points would differ from run to run. Cameras and rigs are numbered in reading order
    already. One camera image per frame (camera_mode PER_IMAGE), as extraction writes them."""
    con = sqlite3.connect(str(database))
    try:
        with con:
            image_id = dict(con.execute("SELECT name, image_id FROM images"))
            frame_of = dict(con.execute("SELECT data_id, frame_id FROM frame_data WHERE sensor_type = ?",
                                        (_CAMERA_SENSOR,)))
            if sorted(image_id) != sorted(names) or len(frame_of) != len(names):
                raise SceneError(database, f"triangulation: the feature database holds {len(image_id)} images and "
                                           f"{len(frame_of)} camera frames for {len(names)} views")
            new_image = {image_id[n]: k for k, n in enumerate(names, 1)}
            new_frame = {frame_of[old]: new for old, new in new_image.items()}
            shift = 1 + max(max(new_image), max(new_frame), len(names))  # via ids no row holds: keys stay unique
            for table, column, new in (("images", "image_id", new_image), ("keypoints", "image_id", new_image),
                                       ("descriptors", "image_id", new_image), ("frame_data", "data_id", new_image),
                                       ("frames", "frame_id", new_frame), ("frame_data", "frame_id", new_frame)):
                con.executemany(f"UPDATE {table} SET {column} = ? WHERE {column} = ?",
                                [(n + shift, old) for old, n in new.items()])
                con.execute(f"UPDATE {table} SET {column} = {column} - ? WHERE {column} >= ?", (shift, shift))
    finally:
        con.close()


_CAMERA_SENSOR = 0  # COLMAP's SensorType::CAMERA in the frame_data table


def _reconstruction_with_poses(database: Path, names: list[str], cameras):
    """A pycolmap Reconstruction holding the database's rigs, cameras, frames and images (same ids, as the
    triangulator requires) with our poses, every frame registered, no points."""
    import pycolmap

    pose = {n: c.viewmat[:3, :4] for n, c in zip(names, cameras)}
    rec = pycolmap.Reconstruction()
    with pycolmap.Database.open(str(database)) as db:
        images = db.read_all_images()
        frame_pose = {im.frame_id: pose[im.name] for im in images}
        for cam in db.read_all_cameras():
            rec.add_camera(cam)
        for rig in db.read_all_rigs():
            rec.add_rig(rig)
        for frame in db.read_all_frames():
            frame.rig_from_world = pycolmap.Rigid3d(frame_pose[frame.frame_id])  # trivial rigs: rig = camera
            rec.add_frame(frame)
        for im in images:
            rec.add_image(im)
        for frame_id in frame_pose:
            rec.register_frame(frame_id)
    return rec


def triangulate_from_poses(cameras, image_paths: Sequence[PathLike], out_dir: PathLike, *,
                           view_ids: Optional[Sequence[int]] = None, n_views: Optional[int] = None,
                           matcher: str = "auto", max_image_size: int = features.MAX_IMAGE_SIZE,
                           num_threads: int = -1, deterministic: bool = True, progress: bool = True,
                           quiet: bool = True, shared_dir: Optional[PathLike] = None) -> Triangulation:
    """Triangulate points seen by `cameras` (native cameras of the given image files, poses and intrinsics kept
    fixed). view_ids: the scene index of each camera (for PointCloud.observed_by over n_views scene views);
    default 0..len-1. deterministic: match on one thread, so every run finds the same points (see RANDOM_SEED);
    False matches on num_threads, faster on many cores. Cached in out_dir and, with shared_dir, in
    shared_dir/<key> for later runs (see the module docstring)."""
    import pycolmap

    cameras, paths = list(cameras), [Path(p) for p in image_paths]
    if len(cameras) != len(paths) or len(cameras) < 2:
        raise ValueError(f"triangulate_from_poses: need >= 2 cameras with one image each, got {len(cameras)} "
                         f"cameras and {len(paths)} images")
    view_ids = list(range(len(cameras))) if view_ids is None else [int(v) for v in view_ids]
    n_views = len(cameras) if n_views is None else int(n_views)
    out_dir = Path(out_dir)
    settings = {"matcher": matcher, "max_image_size": max_image_size, "view_ids": view_ids, "n_views": n_views}
    key = cache_key(cameras, paths, settings)
    stages = Stages(["features", "matching", "triangulation"], prefix="triangulate", enabled=progress)
    shared = Path(shared_dir) / key if shared_dir is not None else None
    for where in (out_dir, shared):
        cached = _load_cached(where, key, n_views) if where is not None else None
        if cached is not None:
            if where != out_dir:
                _save(out_dir, key, cached)  # the run's own copy, as if it had triangulated
                touch(where)  # the shared entry is used now (warpgs-cache drops the least recently used first)
            stages.report(f"{len(cached.points)} points from {where / POINTS_FILE} (cached), mean reprojection "
                          f"error {cached.mean_error:.2f} px")
            return cached

    start = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    database = out_dir / "database.db"
    database.unlink(missing_ok=True)
    model_dir = out_dir / "model"
    shutil.rmtree(model_dir, ignore_errors=True)
    model_dir.mkdir()
    if quiet:
        pycolmap.logging.minloglevel = 2
    image_root, names = _image_root(paths)
    side = max(max(c.width, c.height) for c in cameras)
    with stages.run("features", f"{len(names)} views with known poses, {side} px"):
        features.extract(database, image_root, names, camera_mode="PER_IMAGE", max_image_size=max_image_size,
                         largest_side=side, num_threads=num_threads)
        _number_images_in_order(database, names)
        _set_known_cameras(database, names, cameras)

    row = {n: i for i, n in enumerate(names)}

    def similarity(sorted_names):
        order = [row[n] for n in sorted_names]
        return pose_similarity(np.stack([cameras[i].center for i in order]),
                               np.stack([cameras[i].forward for i in order]))

    used, pair_names, pairs, detail = features.choose_pairs(database, matcher, similarity=similarity)
    with stages.run("matching", detail):
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = RANDOM_SEED
        features.match(database, used, pair_names, pairs, out_dir, num_threads=1 if deterministic else num_threads,
                       verification=verification)

    with stages.run("triangulation", "poses and intrinsics fixed"):
        rec = _reconstruction_with_poses(database, names, cameras)
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = num_threads
        options.random_seed = options.triangulation.random_seed = RANDOM_SEED
        options.triangulation.ignore_two_view_tracks = len(names) > KEEP_TWO_VIEW_TRACKS_UP_TO
        rec = pycolmap.triangulate_points(rec, database, image_root, model_dir, clear_points=True, options=options,
                                          refine_intrinsics=False)
    points = _point_cloud(rec, names, view_ids, n_views)
    if len(points) == 0:
        raise SceneError(out_dir, f"triangulation from {len(names)} known poses found no points "
                                  f"({features.verified_pairs(database)} verified image pairs)")
    mean_error = float(rec.compute_mean_reprojection_error())
    seconds = time.perf_counter() - start
    info = {"points": len(points), "mean_error": mean_error, "seconds": seconds, "views": len(names),
            "pairs": detail, "stage_seconds": dict(stages.times), "image_root": str(image_root)}
    tri = Triangulation(points, mean_error, seconds, False, info)
    _save(out_dir, key, tri)
    if shared is not None:
        try:
            _save(shared, key, tri)
        except OSError as exc:  # a read-only or full cache costs the next run the time, nothing else
            print(f"triangulate: could not cache the points in {shared} ({exc})", file=sys.stderr)
    database.unlink(missing_ok=True)  # hundreds of MB for large sets; the points and the model stay
    stages.report(f"{len(points)} points, mean reprojection error {mean_error:.2f} px, {seconds:.1f} s")
    return tri


def _point_cloud(rec, names: list[str], view_ids: list[int], n_views: int) -> PointCloud:
    ids = sorted(rec.point3D_ids())
    row = {pid: r for r, pid in enumerate(ids)}
    xyz = np.array([rec.points3D[p].xyz for p in ids], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([rec.points3D[p].color for p in ids], dtype=np.float32).reshape(-1, 3) / 255.0
    observed = [np.zeros(0, np.int64) for _ in range(n_views)]
    view_of = dict(zip(names, view_ids))
    for im in rec.images.values():
        pts = im.points2D
        seen = [row[pts[k].point3D_id] for k in im.get_observation_point2D_idxs()]
        observed[view_of[im.name]] = np.unique(np.asarray(seen, np.int64))
    return PointCloud(xyz, rgb, observed)


def triangulate_scene(scene, out_dir: PathLike, *, views: Optional[Sequence[int]] = None, **kwargs) -> Triangulation:
    """Points for a Scene from its own poses, using its training views (or `views`). Cached in out_dir."""
    views = list(scene.train if views is None else views) or list(range(len(scene)))
    return triangulate_from_poses([scene.native_cameras[v] for v in views], [scene.files[v].image for v in views],
                                  out_dir, view_ids=views, n_views=len(scene), **kwargs)
