"""Binary PLY files as named float columns (numpy only): the container format 3DGS/2DGS tools exchange."""
from __future__ import annotations

from typing import Dict, Mapping

import numpy as np

from warpgs.utils.atomic_file import atomic_write_bytes

# PLY: only numpy, binary, scalar properties (what 3DGS/2DGS tools and viewers exchange).
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def write_ply(path, columns: Mapping[str, np.ndarray]) -> None:
    """One `vertex` element of float32 properties, in the given order; temp file + os.replace."""
    names = list(columns)
    if not names:
        raise ValueError("columns: nothing to write")
    n = len(columns[names[0]])
    data = np.empty(n, dtype=[(name, "<f4") for name in names])
    for name in names:
        col = np.asarray(columns[name])
        if col.shape != (n,):
            raise ValueError(f"columns[{name!r}]: expected shape ({n},), got {col.shape}")
        data[name] = col
    header = "\n".join(["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
                       + [f"property float {name}" for name in names] + ["end_header"]) + "\n"
    atomic_write_bytes(path, header.encode("ascii") + data.tobytes())


def read_ply(path) -> Dict[str, np.ndarray]:
    """Columns of the `vertex` element of a binary PLY (little or big endian), in file order.

    The header is untrusted: every count is checked against the bytes the file holds before anything is read,
    and every problem is a ValueError naming the file."""
    with open(path, "rb") as f:
        raw = f.read()
    end = raw.find(b"end_header")
    newline = raw.find(b"\n", end) if end >= 0 else -1
    if not raw.startswith(b"ply") or newline < 0:
        raise ValueError(f"path: {path} is not a PLY file (no 'ply' magic or 'end_header' line)")
    body = newline + 1
    lines = [ln.strip() for ln in raw[:end].decode("ascii", "replace").splitlines()]
    endian = None
    elements = []  # (name, count, [(prop, dtype)])
    for ln in lines[1:]:
        parts = ln.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            fmt = {"binary_little_endian": "<", "binary_big_endian": ">"}
            if len(parts) < 2 or parts[1] not in fmt:
                raise ValueError(f"path: {path}: only binary PLY is supported, got format {' '.join(parts[1:])}")
            endian = fmt[parts[1]]
        elif parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise ValueError(f"path: {path}: bad element line {ln!r:.80} (expected 'element <name> <count>')")
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise ValueError(f"path: {path}: property before any element")
            if len(parts) >= 2 and parts[1] == "list":
                raise ValueError(f"path: {path}: list property {parts[-1]!r} in element {elements[-1][0]!r} is not supported")
            if len(parts) != 3 or parts[1] not in _PLY_TYPES:
                raise ValueError(f"path: {path}: bad property line {ln!r:.80} (expected 'property <type> <name>')")
            if any(parts[2] == p for p, _ in elements[-1][2]):
                raise ValueError(f"path: {path}: property {parts[2]!r} appears twice in element {elements[-1][0]!r}")
            elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
    if endian is None:
        raise ValueError(f"path: {path}: missing 'format' line")
    offset = body
    for name, count, props in elements:
        dtype = np.dtype([(p, endian + t) for p, t in props])
        if name == "vertex":
            if not props:
                raise ValueError(f"path: {path}: the vertex element has no properties")
            if len(raw) < offset + count * dtype.itemsize:
                raise ValueError(f"path: {path}: truncated (vertex data needs {count * dtype.itemsize} bytes, "
                                 f"{max(len(raw) - offset, 0)} follow)")
            data = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
            return {p: np.ascontiguousarray(data[p]) for p, _ in props}
        offset += count * dtype.itemsize
    raise ValueError(f"path: {path}: no 'vertex' element")
