"""transforms.json scenes (NeRF, instant-ngp, nerfstudio) in and out.

Poses there are OpenGL camera-to-world matrices (x right, y up, z backward); we convert them to OpenCV
world-to-camera. Intrinsics may sit at the top level (shared) or in each frame (per-frame wins): fl_x/fl_y or
camera_angle_x/camera_angle_y, cx/cy (default: image centre), w/h (default: read from the image header),
distortion k1, k2, k3, k4, p1, p2 with nerfstudio's camera_model ("OPENCV" or "OPENCV_FISHEYE").
NeRF-synthetic style folders with transforms_train.json / transforms_test.json give the split
(transforms_val.json is not loaded). instant-ngp's aabb_scale/scale/offset only matter to its own sampler
and are ignored: the poses are used as written.
"""
from __future__ import annotations

import errno
import json
import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from warpgs.data.camera import Camera, intrinsics_matrix, opengl_camtoworld_from_viewmat, viewmat_from_opengl_camtoworld
from warpgs.data.errors import MissingSceneFile, PathLike, SceneError, read_json
from warpgs.data.formats.image_io import IMAGE_EXTENSIONS, image_size
from warpgs.data.formats.ply_points import read_ply_points
from warpgs.data.scene import MapFormat, Scene
from warpgs.data.formats.splits import resolve_split
from warpgs.data.formats.view_files import discover_view_files, read_label_names, read_map_format

TRANSFORMS_FILE = "transforms.json"
SPLIT_FILES = {"train": "transforms_train.json", "test": "transforms_test.json"}


def find_transforms(root: PathLike) -> list[Path]:
    root = Path(root)
    if (root / TRANSFORMS_FILE).is_file():
        return [root / TRANSFORMS_FILE]
    return [root / f for f in SPLIT_FILES.values() if (root / f).is_file()]


def _read_json(path: Path) -> dict:
    try:
        data = read_json(path)
    except RecursionError as exc:  # json nests one Python frame per bracket
        raise SceneError(path, "JSON nested too deeply") from exc
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise SceneError(path, 'expected an object with a "frames" list')
    if not data["frames"]:
        raise SceneError(path, "has no frames")
    bad = next((i for i, f in enumerate(data["frames"]) if not isinstance(f, dict)), None)
    if bad is not None:
        raise SceneError(path, f"frame {bad} is not an object")
    return data


def _number(value, key: str, json_path: Path, where: str, positive: bool = False) -> float:
    """A finite JSON number (bools are not numbers here), else SceneError naming the file and key."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or abs(value) > 1e300 or (positive and value <= 0):
        kind = "a positive" if positive else "a finite"
        raise SceneError(json_path, f"{where}: {key} must be {kind} number, got {value!r:.60}")
    return float(value)


def _text(value, key: str, json_path: Path, where: str) -> str:
    if not isinstance(value, str) or not value or "\0" in value:
        raise SceneError(json_path, f"{where}: {key} must be a non-empty string, got {value!r:.60}")
    return value


def _resolve_image(base: Path, file_path: str, json_path: Path) -> Path:
    path = base / file_path
    try:
        path.stat()
    except OSError as exc:  # is_file() raises (not False) for a name too long, so say which entry it was
        if exc.errno not in (errno.ENOENT, errno.ENOTDIR):
            raise SceneError(json_path, f"file_path {file_path!r:.80}: {exc.strerror}") from exc
    if path.suffix in IMAGE_EXTENSIONS:
        return path
    for ext in IMAGE_EXTENSIONS:  # NeRF-synthetic writes "./train/r_0" without the extension
        if Path(str(path) + ext).is_file():
            return Path(str(path) + ext)
    raise MissingSceneFile(path, f"image (listed in {json_path.name})")


def _model_and_distortion(get, json_path: Path, where: str) -> tuple[str, tuple]:
    k1, k2, k3, k4, p1, p2 = (_number(get(k, 0.0), k, json_path, where) for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
    model = get("camera_model", "OPENCV")
    if model == "OPENCV_FISHEYE":
        return "OPENCV_FISHEYE", (k1, k2, k3, k4)
    if not isinstance(model, str) or model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise SceneError(json_path, f"camera_model {model!r:.60} is not supported (use OPENCV or OPENCV_FISHEYE)")
    if k4 != 0.0:
        raise SceneError(json_path, "k4 is only meaningful for OPENCV_FISHEYE")
    if k3 != 0.0:
        return "FULL_OPENCV", (k1, k2, p1, p2, k3, 0.0, 0.0, 0.0)
    if any((k1, k2, p1, p2)):
        return "OPENCV", (k1, k2, p1, p2)
    return "PINHOLE", ()


def _camera_from_frame(frame: dict, top: dict, base: Path, json_path: Path, index: int) -> Camera:
    get = lambda key, default=None: frame.get(key, top.get(key, default))  # noqa: E731
    if "file_path" not in frame or "transform_matrix" not in frame:
        raise SceneError(json_path, f"frame {index} needs 'file_path' and 'transform_matrix'")
    where = f"frame {index}"
    file_path = _text(frame["file_path"], "file_path", json_path, where)
    image_path = _resolve_image(base, file_path, json_path)
    w, h = get("w"), get("h")
    if w is None or h is None:
        w, h = image_size(image_path)
    w, h = (_number(v, k, json_path, where, positive=True) for v, k in ((w, "w"), (h, "h")))
    if w != int(w) or h != int(h) or max(w, h) > 1 << 20:
        raise SceneError(json_path, f"{where}: w and h must be whole numbers of pixels (at most 2^20), got {w}, {h}")
    w, h = int(w), int(h)
    fx = get("fl_x")
    if fx is None and get("camera_angle_x") is not None:
        fx = 0.5 * w / np.tan(0.5 * _number(get("camera_angle_x"), "camera_angle_x", json_path, where))
    fy = get("fl_y")
    if fy is None and get("camera_angle_y") is not None:
        fy = 0.5 * h / np.tan(0.5 * _number(get("camera_angle_y"), "camera_angle_y", json_path, where))
    if fx is None:
        raise SceneError(json_path, f"frame {index} ({file_path}): no focal length (fl_x or camera_angle_x)")
    fy = fx if fy is None else fy
    K = intrinsics_matrix(_number(fx, "fl_x", json_path, where), _number(fy, "fl_y", json_path, where),
                          _number(get("cx", w / 2), "cx", json_path, where),
                          _number(get("cy", h / 2), "cy", json_path, where))
    try:
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise SceneError(json_path, f"frame {index}: transform_matrix is not numeric") from exc
    if c2w.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(c2w)):
        raise SceneError(json_path, f"frame {index}: transform_matrix must be a finite 4x4 or 3x4 matrix")
    model, distortion = _model_and_distortion(get, json_path, where)
    name = str(Path(file_path).as_posix()).removeprefix("./")
    if Path(name).suffix not in IMAGE_EXTENSIONS:
        name = name + image_path.suffix
    try:
        return Camera(K, viewmat_from_opengl_camtoworld(c2w), w, h, name=name, image_path=image_path,
                      model=model, distortion=distortion)
    except ValueError as exc:
        raise SceneError(json_path, f"frame {index}: {exc}") from exc


def _frame_files(frames: list, base: Path, json_path: Path):
    """nerfstudio's per-frame depth_file_path / mask_path, when given."""
    def file(f, key, i):
        return base / _text(f[key], key, json_path, f"frame {i}") if key in f else None

    return [{"depth": file(f, "depth_file_path", i), "mask": file(f, "mask_path", i)} for i, f in enumerate(frames)]


def load_transforms(root: PathLike, *, split=None, n_train: Optional[int] = None, downscale: int = 1,
                    undistort: bool = True, background: Optional[Sequence[float]] = None,
                    validate: bool = True) -> Scene:
    """A transforms.json scene folder -> Scene. No SfM points unless the file names a PLY (ply_file_path);
    use warpgs.data.sfm.init_points for a random or depth-derived initialisation."""
    root = Path(root)
    if not root.is_dir():
        raise MissingSceneFile(root, "scene folder")
    json_paths = find_transforms(root)
    if not json_paths:
        raise MissingSceneFile(root / TRANSFORMS_FILE, "transforms file")
    cameras, extras, parts, top = [], [], {}, {}
    for json_path in json_paths:
        top = _read_json(json_path)
        frames = top["frames"]
        start = len(cameras)
        cameras += [_camera_from_frame(f, top, json_path.parent, json_path, i) for i, f in enumerate(frames)]
        extras += _frame_files(frames, json_path.parent, json_path)
        parts[json_path.name] = list(range(start, len(cameras)))
    names = [c.name for c in cameras]
    if json_paths[0].name == TRANSFORMS_FILE:
        train, test = resolve_split(root, names, split, n_train)
    else:
        train, test = resolve_split(root, names, split if split is not None else (
            parts.get(SPLIT_FILES["train"], []), parts.get(SPLIT_FILES["test"], [])), n_train)
    files = discover_view_files(root, names, [c.image_path for c in cameras])
    for vf, ex in zip(files, extras):
        vf.depth = ex["depth"] or vf.depth
        vf.mask = ex["mask"] or vf.mask
    depth_default = MapFormat("depth", _number(top.get("depth_unit_scale_factor", 1.0), "depth_unit_scale_factor",
                                               json_paths[-1], "top level", positive=True))
    points = None
    if "ply_file_path" in top:
        ply = _text(top["ply_file_path"], "ply_file_path", json_paths[-1], "top level")
        points = read_ply_points(json_paths[0].parent / ply)
    scene = Scene(cameras, files, root=root, train=train, test=test, points=points,
                  label_names=read_label_names(root), depth_format=read_map_format(root, "depth", depth_default),
                  prior_format=read_map_format(root, "depth_prior", MapFormat()), background=background,
                  undistort=undistort, downscale=downscale, source="transforms")
    return scene.validate() if validate else scene


def save_transforms(cameras: Sequence[Camera], path: PathLike, image_prefix: str = "images/") -> Path:
    """Write cameras as a nerfstudio-style transforms.json with per-frame intrinsics and OpenGL poses."""
    frames = []
    for cam in cameras:
        frame = {"file_path": image_prefix + cam.name, "w": cam.width, "h": cam.height, "fl_x": cam.fx,
                 "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy,
                 "transform_matrix": opengl_camtoworld_from_viewmat(cam.viewmat).tolist()}
        d = cam.distortion
        if cam.model == "OPENCV":
            frame.update(camera_model="OPENCV", k1=d[0], k2=d[1], p1=d[2], p2=d[3])
        elif cam.model == "OPENCV_FISHEYE":
            frame.update(camera_model="OPENCV_FISHEYE", k1=d[0], k2=d[1], k3=d[2], k4=d[3])
        elif cam.model in ("SIMPLE_RADIAL", "RADIAL"):
            frame.update(camera_model="OPENCV", k1=d[0], k2=d[1] if len(d) > 1 else 0.0, p1=0.0, p2=0.0)
        elif cam.model == "FULL_OPENCV" and not any(d[5:]):
            frame.update(camera_model="OPENCV", k1=d[0], k2=d[1], p1=d[2], p2=d[3], k3=d[4])
        elif cam.model not in ("PINHOLE", "SIMPLE_PINHOLE"):
            raise ValueError(f"camera {cam.name!r}: model {cam.model} has no transforms.json equivalent")
        frames.append(frame)
    path = Path(path)
    path.write_text(json.dumps({"frames": frames}, indent=1))
    return path
