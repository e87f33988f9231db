"""Find which file of a broken binary COLMAP model is truncated or malformed.

pycolmap's errors do not say which file they came from ("unordered_map::at"), so when reading fails we walk
the documented record layout of cameras.bin, images.bin and points3D.bin and report the first file whose
records run past its end (or leave bytes over). Only used after a failure, so speed does not matter.
"""
from __future__ import annotations

import struct
from pathlib import Path
from typing import Optional


class _Reader:
    def __init__(self, data: bytes):
        self.data, self.pos = data, 0

    def take(self, fmt: str):
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise EOFError
        out = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return out

    def skip(self, n: int):
        if self.pos + n > len(self.data):
            raise EOFError
        self.pos += n

    def cstring(self):
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise EOFError
        self.pos = end + 1


def _num_params(model_id: int) -> int:
    import pycolmap

    return len(pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId(model_id), 1.0, 1, 1).params)


def _walk_cameras(r: _Reader):
    (n,) = r.take("<Q")
    for _ in range(n):
        _, model_id, _, _ = r.take("<IiQQ")
        r.skip(8 * _num_params(model_id))


def _walk_images(r: _Reader):
    (n,) = r.take("<Q")
    for _ in range(n):
        r.take("<I7dI")
        r.cstring()
        (n_pts,) = r.take("<Q")
        r.skip(24 * n_pts)


def _walk_points(r: _Reader):
    (n,) = r.take("<Q")
    for _ in range(n):
        r.take("<Q3d3BdQ")
        track_len = struct.unpack_from("<Q", r.data, r.pos - 8)[0]
        r.skip(8 * track_len)


def find_broken_binary_file(model_dir: Path) -> Optional[Path]:
    for name, walk in (("cameras.bin", _walk_cameras), ("images.bin", _walk_images),
                       ("points3D.bin", _walk_points)):
        path = Path(model_dir) / name
        if not path.is_file():
            continue
        reader = _Reader(path.read_bytes())
        try:
            walk(reader)
        except (EOFError, ValueError, struct.error):
            return path
        if reader.pos != len(reader.data):
            return path
    return None
