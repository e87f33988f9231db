"""Triangle meshes as binary PLY (numpy only): positions, normals and 8-bit colours per vertex, faces as lists
of three int indices, the layout Blender, MeshLab and Open3D read. Written atomically."""
from __future__ import annotations

import numpy as np

from warpgs.data.formats.image_io import to_uint8
from warpgs.mesh.clean import vertex_normals
from warpgs.mesh.volume import Mesh
from warpgs.utils.atomic_file import atomic_write_bytes

VERTEX_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                         ("red", "u1"), ("green", "u1"), ("blue", "u1")])
FACE_DTYPE = np.dtype([("count", "u1"), ("vertex_indices", "<i4", (3,))])


def write_mesh_ply(path, mesh: Mesh, comment: str = "") -> None:
    v = np.empty(len(mesh.vertices), dtype=VERTEX_DTYPE)
    normals = vertex_normals(mesh)
    for k, axis in enumerate("xyz"):
        v[axis] = mesh.vertices[:, k]
        v["n" + axis] = normals[:, k]
    rgb = to_uint8(mesh.colors)
    for k, name in enumerate(("red", "green", "blue")):
        v[name] = rgb[:, k]
    f = np.empty(len(mesh.faces), dtype=FACE_DTYPE)
    f["count"] = 3
    f["vertex_indices"] = mesh.faces
    lines = ["ply", "format binary_little_endian 1.0"]
    # the header is ASCII: a comment naming a run folder like "café" keeps its other characters as \xe9 escapes
    lines += [f"comment {line.encode('ascii', 'backslashreplace').decode('ascii')}"
              for line in comment.splitlines() if line.strip()]
    lines += [f"element vertex {len(v)}"]
    lines += [f"property float {n}" for n in ("x", "y", "z", "nx", "ny", "nz")]
    lines += [f"property uchar {n}" for n in ("red", "green", "blue")]
    lines += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode("ascii") + v.tobytes() + f.tobytes())
