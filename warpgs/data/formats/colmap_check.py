"""Check a binary COLMAP model's record layout before pycolmap reads it.

pycolmap (4.x) trusts the files: it reads past the end without noticing (a truncated file loads as garbage),
loops for as long as a corrupted count says (a huge count in frames.bin, or an image name without its closing
NUL, never returns), reserves memory for a count before reading it (std::bad_alloc) and reports the errors it
does catch without naming the file ("unordered_map::at"). So every count is checked against the bytes left
in its file before anything loops over it, and the files must end exactly after their last record. What is
checked here is the layout COLMAP writes (colmap/scene/reconstruction_io_binary.cc), plus the references a
reader cannot do without (image -> camera, observation -> point, track -> image keypoint); pycolmap still
checks the rest, and its errors are turned into SceneError by the caller.
"""
from __future__ import annotations

import struct
from pathlib import Path
from typing import Optional

import numpy as np

from warpgs.data.errors import SceneError

INVALID_POINT3D_ID = 2**64 - 1  # an image keypoint that observes no 3D point
_CAMERA = struct.Struct("<IiQQ")  # camera_id, model_id, width, height; then the model's params (float64)
_IMAGE = struct.Struct("<I7dI")  # image_id, qw qx qy qz tx ty tz, camera_id; then name, NUL, num_points2D
_POINT = struct.Struct("<Q3d3BdQ")  # point3D_id, xyz, rgb, error, track_length
_RIG = struct.Struct("<II")  # rig_id, num_sensors
_FRAME = struct.Struct("<II7dI")  # frame_id, rig_id, rig_from_world, num_data_ids
_KEYPOINTS = np.dtype([("x", "<f8"), ("y", "<f8"), ("point3D_id", "<u8")])
_TRACK = np.dtype([("image_id", "<u4"), ("point2D_idx", "<u4")])
_COUNT = struct.Struct("<Q")


class _Records:
    """A cursor over one file's bytes whose every read is bounds-checked; errors name the file."""

    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    @property
    def left(self) -> int:
        return len(self.data) - self.pos

    def fail(self, problem: str):
        raise SceneError(self.path, f"malformed binary COLMAP file: {problem} (at byte {self.pos} of {len(self.data)})")

    def take(self, fmt: struct.Struct, what: str) -> tuple:
        if fmt.size > self.left:
            self.fail(f"truncated inside {what}")
        out = fmt.unpack_from(self.data, self.pos)
        self.pos += fmt.size
        return out

    def count(self, what: str, min_record: int) -> int:
        """A u64 record count, refused when even records of the smallest size could not fit in what is left."""
        (n,) = self.take(_COUNT, f"the number of {what}")
        if n * min_record > self.left:
            self.fail(f"declares {n} {what} but only {self.left} bytes follow (each needs at least {min_record})")
        return n

    def array(self, dtype: np.dtype, n: int, what: str) -> np.ndarray:
        if n * dtype.itemsize > self.left:
            self.fail(f"truncated: declares {n} {what} but only {self.left} bytes follow ({dtype.itemsize} each)")
        out = np.frombuffer(self.data, dtype=dtype, count=n, offset=self.pos)
        self.pos += n * dtype.itemsize
        return out

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            self.fail(f"{what} has no terminating NUL byte")
        raw = self.data[self.pos:end]
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            self.fail(f"{what} is not valid UTF-8 ({raw[:40]!r})")
        if not text:
            self.fail(f"{what} is empty")
        self.pos = end + 1
        return text

    def finish(self):
        if self.left:
            self.fail(f"{self.left} bytes left over after the last record")


_NUM_PARAMS: dict = {}


def _num_params(model_id: int) -> Optional[int]:
    """Parameters of a COLMAP camera model (None for ids pycolmap does not know)."""
    if not _NUM_PARAMS:
        import pycolmap

        for model in pycolmap.CameraModelId.__members__.values():
            if int(model) >= 0:
                _NUM_PARAMS[int(model)] = len(pycolmap.Camera.create_from_model_id(1, model, 1.0, 1, 1).params)
    return _NUM_PARAMS.get(model_id)


def _new_id(r: _Records, seen, key, what: str):
    if key in seen:
        r.fail(f"{what} appears twice")


def _check_cameras(path: Path) -> set:
    r = _Records(path)
    ids = set()
    for i in range(r.count("cameras", _CAMERA.size)):
        camera_id, model_id, _, _ = r.take(_CAMERA, f"camera {i}")
        params = _num_params(model_id)
        if params is None:
            r.fail(f"camera {camera_id} has unknown camera model id {model_id}")
        r.array(np.dtype("<f8"), params, f"parameters of camera {camera_id}")
        _new_id(r, ids, camera_id, f"camera id {camera_id}")
        ids.add(camera_id)
    r.finish()
    return ids


def _check_images(path: Path, camera_ids: set, frame_of: Optional[dict]) -> tuple[dict, np.ndarray]:
    """{image_id: number of keypoints}, and every keypoint's point3D_id. frame_of: {image_id: frame_id} from
    frames.bin (None for models written before COLMAP had rigs and frames)."""
    r = _Records(path)
    keypoints, observed = {}, []
    for i in range(r.count("images", _IMAGE.size + 1 + _COUNT.size)):
        image_id, *_, camera_id = r.take(_IMAGE, f"image {i}")
        r.name(f"the name of image {image_id}")
        (n,) = r.take(_COUNT, f"the keypoint count of image {image_id}")
        observed.append(r.array(_KEYPOINTS, n, f"keypoints of image {image_id}")["point3D_id"])
        if camera_id not in camera_ids:
            r.fail(f"image {image_id} refers to camera {camera_id}, which cameras.bin does not hold")
        if frame_of is not None and frame_of.get(image_id, (None, None))[1] != camera_id:
            r.fail(f"image {image_id} (camera {camera_id}) is the data of no frame in frames.bin with that camera")
        _new_id(r, keypoints, image_id, f"image id {image_id}")
        keypoints[image_id] = n
    r.finish()
    return keypoints, np.concatenate(observed) if observed else np.zeros(0, np.uint64)


def read_points3d(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """points3D.bin's records, every read bounds-checked: (ids [N] uint64, xyz [N, 3] float64, mean reprojection
    errors [N], tracks: N structured arrays of (image_id, point2D_idx)). A malformed file is a SceneError naming it."""
    r = _Records(Path(path))
    ids, xyz, errors, tracks = [], [], [], []
    for i in range(r.count("points", _POINT.size)):
        point_id, x, y, z, _, _, _, error, track_length = r.take(_POINT, f"point {i}")
        tracks.append(r.array(_TRACK, track_length, f"track elements of point {point_id}"))
        ids.append(point_id)
        xyz.append((x, y, z))
        errors.append(error)
    r.finish()
    return (np.asarray(ids, dtype=np.uint64), np.asarray(xyz, dtype=np.float64).reshape(-1, 3),
            np.asarray(errors, dtype=np.float64), tracks)


def _check_points(path: Path, keypoints: dict) -> np.ndarray:
    ids, _, _, tracks = read_points3d(path)
    r = _Records(path)  # for its error messages only
    if tracks:
        track = np.concatenate(tracks)
        if len(track) and not keypoints:
            r.fail(f"a track refers to image {int(track['image_id'][0])}, but images.bin holds no images")
        image_ids = np.fromiter(keypoints, dtype=np.int64, count=len(keypoints))
        sizes = np.fromiter(keypoints.values(), dtype=np.int64, count=len(keypoints))
        order = np.argsort(image_ids)
        at = np.searchsorted(image_ids[order], track["image_id"])
        known = (at < len(order)) & (image_ids[order][np.minimum(at, len(order) - 1)] == track["image_id"])
        if not known.all():
            r.fail(f"a track refers to image {int(track['image_id'][~known][0])}, which images.bin does not hold")
        bad = track["point2D_idx"] >= sizes[order][at]
        if bad.any():
            r.fail(f"a track refers to keypoint {int(track['point2D_idx'][bad][0])} of image "
                   f"{int(track['image_id'][bad][0])}, which has fewer keypoints")
    return ids


_SENSOR_TYPES = {0: "camera", 1: "IMU"}  # pycolmap.SensorType


def _sensor(r: _Records, fmt: struct.Struct, what: str, camera_ids: set) -> tuple:
    kind, sensor_id, *rest = r.take(fmt, what)
    if kind not in _SENSOR_TYPES:
        r.fail(f"{what} has unknown sensor type {kind}")
    if kind == 0 and sensor_id not in camera_ids:
        r.fail(f"{what} is camera {sensor_id}, which cameras.bin does not hold")
    return (kind, sensor_id), rest


def _check_rigs(path: Path, camera_ids: set) -> dict:
    """{rig_id: its sensors as (type, id)}."""
    r = _Records(path)
    rigs: dict = {}
    for i in range(r.count("rigs", _RIG.size)):
        rig_id, sensors = r.take(_RIG, f"rig {i}")
        if sensors > r.left // 8:  # each sensor takes at least its (type, id)
            r.fail(f"rig {rig_id} declares {sensors} sensors but only {r.left} bytes follow")
        _new_id(r, rigs, rig_id, f"rig id {rig_id}")
        rigs[rig_id] = set()
        if sensors:
            rigs[rig_id].add(_sensor(r, struct.Struct("<iI"), f"the reference sensor of rig {rig_id}", camera_ids)[0])
        for _ in range(max(sensors - 1, 0)):
            sensor, (has_pose,) = _sensor(r, struct.Struct("<iIB"), f"a sensor of rig {rig_id}", camera_ids)
            _new_id(r, rigs[rig_id], sensor, f"sensor {sensor} of rig {rig_id}")
            rigs[rig_id].add(sensor)
            if has_pose:
                r.take(struct.Struct("<7d"), f"a sensor pose of rig {rig_id}")
    r.finish()
    return rigs


def _check_frames(path: Path, rigs: dict) -> dict:
    """{image_id: (frame_id, camera_id)} for every camera datum of a frame."""
    r = _Records(path)
    frames, frame_of = set(), {}
    data = np.dtype([("type", "<i4"), ("sensor_id", "<u4"), ("data_id", "<u8")])
    for i in range(r.count("frames", _FRAME.size)):
        frame_id, rig_id, *_, n = r.take(_FRAME, f"frame {i}")
        _new_id(r, frames, frame_id, f"frame id {frame_id}")
        frames.add(frame_id)
        if rig_id not in rigs:
            r.fail(f"frame {frame_id} refers to rig {rig_id}, which rigs.bin does not hold")
        for kind, sensor_id, data_id in r.array(data, n, f"data ids of frame {frame_id}").tolist():
            if (kind, sensor_id) not in rigs[rig_id]:
                r.fail(f"frame {frame_id} holds data of sensor {(kind, sensor_id)}, which rig {rig_id} lacks")
            if kind == 0:
                _new_id(r, frame_of, data_id, f"image {data_id} (in frame {frame_id})")
                frame_of[data_id] = (frame_id, sensor_id)
    r.finish()
    return frame_of


def check_binary_model(model_dir) -> None:
    """Raise SceneError naming the first file of a binary COLMAP model whose layout or references are broken."""
    model_dir = Path(model_dir)
    camera_ids = _check_cameras(model_dir / "cameras.bin")
    frame_of = None
    if (model_dir / "rigs.bin").is_file() and (model_dir / "frames.bin").is_file():  # COLMAP >= 3.12
        frame_of = _check_frames(model_dir / "frames.bin", _check_rigs(model_dir / "rigs.bin", camera_ids))
    keypoints, observed = _check_images(model_dir / "images.bin", camera_ids, frame_of)
    point_ids = _check_points(model_dir / "points3D.bin", keypoints)
    observed = observed[observed != INVALID_POINT3D_ID]
    missing = observed[~np.isin(observed, point_ids)]
    if len(missing):
        raise SceneError(model_dir / "images.bin", f"a keypoint observes point {int(missing[0])}, which points3D.bin "
                                                   "does not hold")


def find_broken_binary_file(model_dir) -> Optional[Path]:
    """The file `check_binary_model` blames, or None when the layout is sound."""
    try:
        check_binary_model(model_dir)
    except SceneError as exc:
        return exc.path
    return None
