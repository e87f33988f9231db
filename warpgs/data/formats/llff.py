"""LLFF scenes (forward-facing and sparse-view benchmarks): poses_bounds.npy + images/ (+ images_N/).

poses_bounds.npy is an [N, 17] float array, one row per image in sorted file-name order. Each row is a 3x5
matrix (row-major, 15 numbers) followed by the near and far scene depth of that view. The 3x5 matrix holds the
camera-to-world rotation with its columns in LLFF's order [down, right, back], then the camera centre, then
[height, width, focal] of the full-resolution images (pinhole, principal point at the image centre). Its world
frame is the COLMAP model's the poses came from. In OpenCV axes (ours: x right, y down, z forward):
    right = column 1,  down = column 0,  forward = -column 2.

images_N/ folders hold the same views 1/N the size, named in the same sorted order (not always with the same
names: fern's images_8 has image000.png, ...). When the requested downscale has a complete images_N folder of
the right size they are the stored images; otherwise images/ is resized through the image cache.
Default split: split.json when present, else the LLFF protocol (views 0, 8, 16, ... held out; with n_train,
that many training views spread evenly over the rest, as FSGS and DNGaussian pick them: splits.llff_split).
A complete COLMAP model in sparse/0 whose poses agree with poses_bounds.npy contributes its points, except to a
few-view scene (n_train given): those points were triangulated from every view, held-out ones included, so a
few-view run must make its own from its training views (model.init=triangulate; compute_depth_priors does).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from warpgs.data.camera import Camera, intrinsics_matrix, invert_rigid
from warpgs.data.errors import MissingSceneFile, PathLike, SceneError
from warpgs.data.formats.image_io import image_size, list_images
from warpgs.data.formats.splits import SPLIT_FILE, resolve_split
from warpgs.data.formats.view_files import discover_view_files, read_label_names, read_map_format
from warpgs.data.points import PointCloud
from warpgs.data.scene import MapFormat, Scene

POSES_FILE = "poses_bounds.npy"
# Poses that a COLMAP model must reproduce (rotation in degrees, centre relative to the camera spread) for its
# points to be used with them.
_AGREE_DEG, _AGREE_CENTRE = 0.01, 1e-4


def find_poses(root: PathLike) -> Optional[Path]:
    path = Path(root) / POSES_FILE
    return path if path.is_file() else None


# --- the pose convention -------------------------------------------------------------------------------------------
def viewmat_from_llff(pose: np.ndarray) -> np.ndarray:
    """One 3x5 (or 3x4) LLFF pose -> OpenCV world-to-camera 4x4."""
    pose = np.asarray(pose, dtype=np.float64)
    down, right, back, centre = pose[:, 0], pose[:, 1], pose[:, 2], pose[:, 3]
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, -back, centre
    return invert_rigid(c2w)


def llff_from_viewmat(viewmat: np.ndarray, height: float, width: float, focal: float) -> np.ndarray:
    """OpenCV world-to-camera 4x4 + [h, w, f] -> the 3x5 LLFF matrix (inverse of viewmat_from_llff)."""
    c2w = invert_rigid(np.asarray(viewmat, dtype=np.float64))
    return np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3], [height, width, focal]], axis=1)


def read_poses_bounds(path: PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(viewmats [N, 4, 4], hwf [N, 3], near/far bounds [N, 2]); errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise MissingSceneFile(path, "LLFF poses file")
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise SceneError(path, f"unreadable or truncated .npy file ({exc})") from exc
    if arr.ndim != 2 or arr.shape[1] != 17 or len(arr) == 0:
        raise SceneError(path, f"expected an [N, 17] array (3x5 pose + near, far per view), got shape {arr.shape}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise SceneError(path, "contains NaN or Inf")
    poses = arr[:, :15].reshape(-1, 3, 5)
    hwf, bounds = poses[:, :, 4], arr[:, 15:17]
    if np.any(hwf <= 0):
        raise SceneError(path, "image height, width and focal length (column 5 of each pose) must be positive")
    rot = poses[:, :, :3]
    if not np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-4):
        raise SceneError(path, "pose rotations are not orthonormal")
    if np.any(np.linalg.det(rot) < 0):  # [down, right, back] swaps two axes and flips one: still a rotation
        bad = int(np.nonzero(np.linalg.det(rot) < 0)[0][0])
        raise SceneError(path, f"pose {bad}: rotation is a reflection (determinant -1), not an LLFF pose")
    return np.stack([viewmat_from_llff(p) for p in poses]), hwf, bounds


def save_poses_bounds(cameras: Sequence[Camera], path: PathLike, bounds) -> Path:
    """Write pinhole cameras (fx == fy, principal point at the image centre, as LLFF assumes) as poses_bounds.npy.
    bounds: [N, 2] near/far per view, or one (near, far) pair for all."""
    bounds = np.broadcast_to(np.asarray(bounds, dtype=np.float64), (len(cameras), 2))
    rows = []
    for cam in cameras:
        if cam.has_distortion or not np.isclose(cam.fx, cam.fy, rtol=1e-6) or not np.allclose(
                [cam.cx, cam.cy], [cam.width / 2, cam.height / 2], atol=1e-6 * max(cam.width, cam.height)):
            raise ValueError(f"camera {cam.name!r}: LLFF stores only undistorted cameras with fx == fy and the "
                             f"principal point at the image centre")
        rows.append(llff_from_viewmat(cam.viewmat, cam.height, cam.width, cam.fx).reshape(-1))
    path = Path(path)
    np.save(path, np.concatenate([np.stack(rows), bounds], axis=1))
    return path


# --- which image files ---------------------------------------------------------------------------------------------
def _has_model_file(model: Path, stem: str) -> bool:
    return any((model / f"{stem}{ext}").is_file() for ext in (".bin", ".txt"))


def _model_names(root: Path) -> Optional[list[str]]:
    """Sorted registered image names of a complete COLMAP model next to the poses (LLFF drops the images COLMAP
    could not register, so these are the names its rows belong to)."""
    from warpgs.data.formats import colmap

    model = colmap.find_model(root)
    if model is None or not _has_model_file(model, "images"):
        return None
    return sorted(c.name for c in colmap.cameras_from_model(colmap.read_model(model), root / "images")[0])


def _full_images(root: Path, n: int, poses_path: Path) -> list[Path]:
    folder = root / "images"
    if not folder.is_dir():
        raise MissingSceneFile(folder, "image folder (LLFF scenes keep full-resolution images in images/)")
    files = list_images(folder)
    if len(files) == n:
        return files
    names = _model_names(root) if len(files) > n else None
    if names is not None and len(names) == n and all((folder / m).is_file() for m in names):
        return [folder / m for m in names]
    raise SceneError(poses_path, f"{n} poses but {len(files)} images in {folder} (rows belong to the sorted image "
                                 f"names; a complete sparse/0 model can say which images were registered)")


def _shipped_images(root: Path, factor: int, full: list[Path]) -> Optional[list[Path]]:
    """The images_<factor> files in row order when that folder is complete and 1/factor the size, else None."""
    folder = root / f"images_{factor}"
    if factor == 1 or not folder.is_dir():
        return None
    files = list_images(folder)
    if len(files) != len(full):
        return None
    by_name = {p.name: p for p in files}
    if all(p.name in by_name for p in full):
        files = [by_name[p.name] for p in full]  # same names: pair by name, not position
    for small, big in ((files[0], full[0]), (files[-1], full[-1])):
        w, h = image_size(big)
        sw, sh = image_size(small)
        if abs(sw - w / factor) > 1 or abs(sh - h / factor) > 1:
            return None
    return files


def _only_shipped_images(root: Path, n: int, factor: int) -> Optional[list[Path]]:
    """images_<factor> when images/ is absent (a copy trimmed to the resolution in use) and it holds one image per
    pose; the poses' hwf then says the scale."""
    folder = root / f"images_{factor}"
    if factor == 1 or (root / "images").is_dir() or not folder.is_dir():
        return None
    files = list_images(folder)
    return files if len(files) == n else None


def _has_view_maps(root: Path, names: list[str], paths: list[Path]) -> bool:
    files = discover_view_files(root, names, paths)
    return any(getattr(f, k) is not None for f in files for k in ("depth", "depth_prior", "mask", "labels"))


# --- cameras -------------------------------------------------------------------------------------------------------
def _cameras(viewmats, hwf, names, paths, sizes, poses_path) -> list[Camera]:
    cams = []
    for i, (vm, (h, w, f), name, path, (iw, ih)) in enumerate(zip(viewmats, hwf, names, paths, sizes)):
        sx, sy = iw / w, ih / h
        if abs(sx - sy) > 0.01 * max(sx, sy):
            raise SceneError(poses_path, f"view {i} ({name}): image {path} is {iw}x{ih}, which is not a scaled "
                                         f"copy of the {w:g}x{h:g} the poses were made for")
        K = intrinsics_matrix(f * sx, f * sy, iw / 2.0, ih / 2.0)
        cams.append(Camera(K, vm, iw, ih, name=name, image_path=path, model="PINHOLE"))
    return cams


def colmap_points(root: Path, cameras: Sequence[Camera]) -> Optional[PointCloud]:
    """Points of a complete sparse/0 model when its poses are the LLFF ones (same world frame, every view
    registered), else None. Compared directly, without a similarity: LLFF writes COLMAP's poses unchanged."""
    from warpgs.data.formats import colmap

    model = colmap.find_model(root)
    if model is None or not all(_has_model_file(model, stem) for stem in colmap.MODEL_FILES):
        return None
    rec = colmap.read_model(model)
    ref, ids = colmap.cameras_from_model(rec, root / "images")
    by_name = {c.name: (c, iid) for c, iid in zip(ref, ids)}
    if not all(c.name in by_name for c in cameras):
        return None
    spread = max(float(np.ptp(np.stack([c.center for c in cameras]), axis=0).max()), 1e-9)
    for cam in cameras:
        other = by_name[cam.name][0]
        rel = cam.viewmat[:3, :3] @ other.viewmat[:3, :3].T
        angle = np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0)))
        if angle > _AGREE_DEG or np.linalg.norm(cam.center - other.center) > _AGREE_CENTRE * spread:
            return None
    return colmap.points_from_model(rec, [by_name[c.name][1] for c in cameras])


def load_llff(root: PathLike, *, split=None, n_train: Optional[int] = None, downscale: int = 1,
              undistort: bool = True, validate: bool = True) -> Scene:
    """An LLFF folder -> Scene (see the module docstring). `undistort` is accepted for symmetry with the other
    loaders; LLFF cameras are pinhole."""
    root = Path(root)
    if not root.is_dir():
        raise MissingSceneFile(root, "scene folder")
    poses_path = root / POSES_FILE
    viewmats, hwf, bounds = read_poses_bounds(poses_path)
    only_small = _only_shipped_images(root, len(viewmats), downscale)
    full = only_small or _full_images(root, len(viewmats), poses_path)
    names = [p.name for p in full]
    shipped = only_small or _shipped_images(root, downscale, full)
    if shipped is not None and _has_view_maps(root, names, full):
        shipped = None  # masks/depth are checked against full-size cameras: resize images/ instead
    paths = shipped or full
    sizes = [image_size(p) for p in paths]
    cameras = _cameras(viewmats, hwf, names, paths, sizes, poses_path)
    if split is None and not (root / SPLIT_FILE).is_file():
        split = "llff"
    train, test = resolve_split(root, names, split, n_train)
    files = discover_view_files(root, names, paths)
    metadata = {"near_far": bounds.tolist(), "images": paths[0].parent.name, "llff_downscale": downscale}
    # Few-view runs never see the all-view model's points (test-view leakage); see the module docstring.
    points = colmap_points(root, cameras) if n_train is None else None
    if n_train is not None:
        metadata["colmap_points"] = "withheld: made from all views, and this is a few-view (n_train) scene"
    scene = Scene(cameras, files, root=root, train=train, test=test, points=points,
                  label_names=read_label_names(root), depth_format=read_map_format(root, "depth", MapFormat("depth")),
                  prior_format=read_map_format(root, "depth_prior", MapFormat()), undistort=undistort,
                  downscale=1 if shipped else downscale, source=f"llff ({paths[0].parent.name})",
                  metadata=metadata)
    return scene.validate() if validate else scene


__all__ = ["POSES_FILE", "find_poses", "load_llff", "read_poses_bounds", "save_poses_bounds", "viewmat_from_llff",
           "llff_from_viewmat", "colmap_points"]
