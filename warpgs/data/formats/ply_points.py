"""A scene's PLY point cloud (nerfstudio's ply_file_path), read through pycolmap after a header check.

pycolmap reserves memory for the vertex count its header declares before reading any vertex, so a corrupted
count (up to 2^32) is a std::bad_alloc, and its errors do not name the file. The header is checked here
first: a binary file must hold the bytes its vertices need, an ASCII one at least a line per vertex.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from warpgs.data.errors import MissingSceneFile, SceneError
from warpgs.data.points import PointCloud

_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
          "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
_MAX_HEADER = 1 << 16  # bytes: a PLY header is a few hundred


def _check_header(path: Path) -> None:
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER)
        size = f.seek(0, 2)
    end = head.find(b"end_header")
    newline = head.find(b"\n", end) if end >= 0 else -1
    if not head.startswith(b"ply") or newline < 0:
        raise SceneError(path, "not a PLY file (no 'ply' magic or no 'end_header' line)")
    lines = head[:end].decode("ascii", "replace").splitlines()
    fmt, count, row, fixed, element = None, None, 0, True, None
    for line in lines[1:]:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format" and len(parts) >= 2:
            fmt = parts[1]
        elif parts[0] == "element":
            element = parts[1] if len(parts) > 1 else None
            if element == "vertex":
                if count is not None or len(parts) != 3 or not parts[2].isdigit():
                    raise SceneError(path, f"PLY header: bad vertex element line {line.strip()!r}")
                count = int(parts[2])
        elif parts[0] == "property" and element == "vertex":
            if len(parts) < 3 or (parts[1] != "list" and parts[1] not in _SIZES):
                raise SceneError(path, f"PLY header: bad vertex property line {line.strip()!r}")
            fixed = fixed and parts[1] != "list"
            row += _SIZES.get(parts[1], 0)
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise SceneError(path, f"PLY header: unknown format {fmt!r}")
    if count is None:
        raise SceneError(path, "PLY header declares no vertex element")
    body = size - (newline + 1)
    need = count * row if fmt != "ascii" and fixed else count  # ASCII: at least one byte (a newline) per vertex
    if need > body:
        raise SceneError(path, f"PLY declares {count} vertices but only {body} bytes of data follow the header")


def read_ply_points(path: Path) -> PointCloud:
    """Positions and colours of a PLY point cloud; errors name the file."""
    import pycolmap

    path = Path(path)
    if not path.is_file():
        raise MissingSceneFile(path, "point cloud (ply_file_path)")
    _check_header(path)
    rec = pycolmap.Reconstruction()
    try:
        rec.import_PLY(str(path))
    except Exception as exc:  # pycolmap raises ValueError, IndexError, MemoryError... depending on the damage
        raise SceneError(path, f"unreadable PLY point cloud ({type(exc).__name__}: {exc})") from exc
    pts = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(xyz)) or (len(xyz) and np.abs(xyz).max() > np.finfo(np.float32).max):
        raise SceneError(path, "PLY point positions must be finite (float32)")
    return PointCloud(xyz.astype(np.float32), np.array([p.color for p in pts]).reshape(-1, 3) / 255.0)
