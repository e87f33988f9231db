"""COLMAP models (text or binary) through pycolmap, in and out.

Expected layout:  <root>/images/...  and  <root>/sparse/0/{cameras,images,points3D}.{bin,txt}
(also accepted: <root>/sparse/ or <root>/ holding the model files), optional <root>/split.json.
pycolmap is imported inside functions so that `import warpgs` needs only warp and torch.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from warpgs.data.camera import Camera
from warpgs.data.formats.colmap_check import check_binary_model, find_broken_binary_file
from warpgs.data.errors import MissingSceneFile, PathLike, SceneError
from warpgs.data.points import PointCloud
from warpgs.data.scene import MapFormat, Scene
from warpgs.data.formats.splits import resolve_split
from warpgs.data.formats.view_files import discover_view_files, read_label_names, read_map_format

MODEL_FILES = ("cameras", "images", "points3D")


def find_model(root: PathLike) -> Optional[Path]:
    """The folder holding the COLMAP model under `root`, or None."""
    root = Path(root)
    for cand in (root / "sparse" / "0", root / "sparse", root):
        if any((cand / f"cameras{ext}").is_file() for ext in (".bin", ".txt")):
            return cand
    return None


def _guess_culprit(model_dir: Path, ext: str, message: str) -> Path:
    # pycolmap's errors cite its own source lines; map the words they contain back to the file being parsed.
    low = message.lower()
    for word, stem in (("point3d", "points3D"), ("image", "images"), ("frame", "frames"), ("rig", "rigs"),
                       ("camera", "cameras")):
        if word in low and (model_dir / f"{stem}{ext}").is_file():
            return model_dir / f"{stem}{ext}"
    return model_dir


def read_model(model_dir: PathLike):
    """pycolmap.Reconstruction from a text or binary model; errors name the file."""
    import pycolmap

    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise MissingSceneFile(model_dir, "COLMAP model folder")
    ext = ".bin" if (model_dir / "cameras.bin").is_file() else ".txt"
    for stem in MODEL_FILES:
        if not (model_dir / f"{stem}{ext}").is_file():
            raise MissingSceneFile(model_dir / f"{stem}{ext}", "COLMAP model file")
    if ext == ".bin":
        check_binary_model(model_dir)  # pycolmap would hang, over-allocate or read garbage on a broken layout
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises ValueError, IndexError, RuntimeError... depending on the damage
        culprit = find_broken_binary_file(model_dir) if ext == ".bin" else None
        culprit = culprit or _guess_culprit(model_dir, ext, str(exc))
        raise SceneError(culprit, f"COLMAP model is truncated or malformed (pycolmap: {exc})") from exc


def _has_pose(im) -> bool:
    return im.has_pose if hasattr(im, "has_pose") else im.registered  # pycolmap >= 3.12 / older


def _cam_from_world(im):
    pose = im.cam_from_world  # a method in pycolmap >= 3.12, a property before
    return pose() if callable(pose) else pose


def _model_file(model_dir: Optional[PathLike], stem: str) -> Optional[Path]:
    """The model file errors about `stem` records should name (binary or text), or the folder."""
    if model_dir is None:
        return None
    for ext in (".bin", ".txt"):
        if (Path(model_dir) / f"{stem}{ext}").is_file():
            return Path(model_dir) / f"{stem}{ext}"
    return Path(model_dir)


def cameras_from_model(rec, images_dir: Path, model_dir: Optional[PathLike] = None) -> tuple[list[Camera], list[int]]:
    """Registered images sorted by name -> (cameras, COLMAP image ids in the same order).
    model_dir: where `rec` was read from, so that errors (a NaN pose, a zero focal length) name the file."""
    try:
        entries = sorted(((im.name, iid) for iid, im in rec.images.items() if _has_pose(im)), key=lambda e: e[0])
    except UnicodeDecodeError as exc:  # text models are not checked beforehand
        raise SceneError(_model_file(model_dir, "images"), f"an image name is not valid UTF-8 ({exc})") from exc
    cameras = []
    for name, iid in entries:
        im = rec.images[iid]
        viewmat = np.eye(4)
        viewmat[:3, :] = _cam_from_world(im).matrix()
        try:
            cameras.append(Camera.from_pycolmap(rec.cameras[im.camera_id], viewmat, name, images_dir / name))
        except ValueError as exc:  # a bad pose is the image's record; size and intrinsics are its camera's
            stem = "images" if "viewmat" in str(exc) else "cameras"
            raise SceneError(_model_file(model_dir, stem), f"image {iid} ({name}), camera {im.camera_id}: {exc}") from exc
    return cameras, [iid for _, iid in entries]


def points_from_model(rec, image_ids: Sequence[int], model_dir: Optional[PathLike] = None) -> Optional[PointCloud]:
    if rec.num_points3D() == 0:
        return None
    # One pass over pycolmap's map: a lookup by id copies the point with its track (bonsai800, 122k points: 0.27 s a
    # field by id against 0.10 s for the pass).
    points = sorted(rec.points3D.items(), key=lambda item: item[0])
    row = {pid: r for r, (pid, _) in enumerate(points)}
    xyz = np.array([p.xyz for _, p in points], dtype=np.float64)
    if not np.all(np.isfinite(xyz)) or np.abs(xyz).max() > np.finfo(np.float32).max:
        raise SceneError(_model_file(model_dir, "points3D"), "3D point positions must be finite (float32)")
    rgb = np.array([p.color for _, p in points], dtype=np.float32) / 255.0
    observed = []
    for iid in image_ids:
        seen = [p.point3D_id for p in rec.images[iid].get_observation_points2D()]
        if any(pid not in row for pid in seen):
            raise SceneError(_model_file(model_dir, "images"), f"image {iid} observes a 3D point the model lacks")
        observed.append(np.unique([row[pid] for pid in seen]).astype(np.int64))
    return PointCloud(xyz.astype(np.float32), rgb, observed)


def load_colmap(root: PathLike, *, model_dir: Optional[PathLike] = None, images_dir: Optional[PathLike] = None,
                split=None, n_train: Optional[int] = None, downscale: int = 1, undistort: bool = True,
                validate: bool = True) -> Scene:
    """A COLMAP scene folder -> Scene (see module docstring for the layout).

    split: None (split.json if present, else all train), "llff", "all" or a (train, test) index pair.
    n_train: a few-view scene; it gets no SfM points (they were made from every view).
    """
    root = Path(root)
    if not root.is_dir():
        raise MissingSceneFile(root, "scene folder")
    model_dir = Path(model_dir) if model_dir is not None else find_model(root)
    if model_dir is None:
        raise SceneError(root, "no COLMAP model found (looked for sparse/0, sparse/ and the folder itself)")
    images_dir = Path(images_dir) if images_dir is not None else root / "images"
    if not images_dir.is_dir():
        raise MissingSceneFile(images_dir, "image folder")
    rec = read_model(model_dir)
    cameras, image_ids = cameras_from_model(rec, images_dir, model_dir)
    if not cameras:
        raise SceneError(model_dir, "COLMAP model has no registered images")
    names = [c.name for c in cameras]
    train, test = resolve_split(root, names, split, n_train)
    # A few-view run (n_train) must not start from points the model triangulated with every view, held-out ones
    # included: it gets none, and model.init=auto triangulates from its training views (as the LLFF loader).
    points = points_from_model(rec, image_ids, model_dir) if n_train is None else None
    scene = Scene(cameras, discover_view_files(root, names, [c.image_path for c in cameras]), root=root,
                  train=train, test=test, points=points,
                  label_names=read_label_names(root),
                  depth_format=read_map_format(root, "depth", MapFormat("depth")),
                  prior_format=read_map_format(root, "depth_prior", MapFormat()),
                  undistort=undistort, downscale=downscale, source="colmap")
    return scene.validate() if validate else scene


def save_colmap(cameras: Sequence[Camera], out_dir: PathLike, points: Optional[PointCloud] = None,
                binary: bool = False) -> Path:
    """Write cameras (and points with their observing views) as a COLMAP model through pycolmap.

    Cameras with identical intrinsics share one COLMAP camera. Each point observed by a view becomes a 2D
    observation at its projection, so the model's tracks say which points each view sees.
    """
    import pycolmap

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rec = pycolmap.Reconstruction()
    intrinsics: dict = {}
    projections = []
    for i, cam in enumerate(cameras):
        key = (cam.model, cam.width, cam.height, tuple(cam.K.ravel()), cam.distortion)
        if key not in intrinsics:
            intrinsics[key] = len(intrinsics) + 1
            rec.add_camera_with_trivial_rig(cam.to_pycolmap(intrinsics[key]))
        obs = [] if points is None or points.observed_by is None else points.observed_by[i]
        xy = cam.project(points.xyz[obs])[0] if len(obs) else np.zeros((0, 2))
        projections.append(obs)
        image = pycolmap.Image(name=cam.name, keypoints=xy.astype(np.float64), camera_id=intrinsics[key],
                               image_id=i + 1)
        pose = pycolmap.Rigid3d(cam.viewmat[:3, :4])
        rec.add_image_with_trivial_frame(image, pose)
    if points is not None:
        tracks = [pycolmap.Track() for _ in range(len(points))]
        for i, obs in enumerate(projections):
            for k, p in enumerate(obs):
                tracks[p].add_element(i + 1, k)
        colours = np.clip(np.round(points.rgb * 255), 0, 255).astype(np.uint8)
        for p in range(len(points)):
            rec.add_point3D(points.xyz[p].astype(np.float64), tracks[p], colours[p])
    (rec.write if binary else rec.write_text)(str(out_dir))
    return out_dir
