"""Mesh clean-up after marching cubes (numpy only): drop degenerate faces, small connected pieces and the
vertices no face uses; per-vertex normals."""
from __future__ import annotations

import numpy as np

from warpgs.mesh.volume import Mesh


def connected_components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Component label of every vertex (the smallest vertex index of its component), two vertices joined when a
    face holds both. Hooking roots onto smaller roots then pointer jumping, vectorised: O(log) rounds."""
    parent = np.arange(n_vertices, dtype=np.int64)
    if len(faces) == 0:
        return parent
    a = np.concatenate([faces[:, 0], faces[:, 1]]).astype(np.int64)
    b = np.concatenate([faces[:, 1], faces[:, 2]]).astype(np.int64)
    while True:
        pa, pb = parent[a], parent[b]  # roots: parent is fully compressed here
        differ = pa != pb
        if not differ.any():
            return parent
        lo, hi = np.minimum(pa[differ], pb[differ]), np.maximum(pa[differ], pb[differ])
        np.minimum.at(parent, hi, lo)
        while True:
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand


def remove_small_components(mesh: Mesh, min_fraction: float = 0.01, min_faces: int = 0) -> Mesh:
    """Keep the connected pieces with at least min_fraction of the largest piece's faces and min_faces faces."""
    faces = mesh.faces
    if len(faces) == 0:
        return mesh
    labels = connected_components(faces, len(mesh.vertices))[faces[:, 0]]
    _, inverse, sizes = np.unique(labels, return_inverse=True, return_counts=True)
    keep_piece = (sizes >= min_fraction * sizes.max()) & (sizes >= min_faces)
    return compact(Mesh(mesh.vertices, faces[keep_piece[inverse]], mesh.colors))


def drop_degenerate_faces(mesh: Mesh, eps: float = 1e-12) -> Mesh:
    """Faces with a repeated vertex or (numerically) zero area."""
    f = mesh.faces
    area2 = np.linalg.norm(face_cross(mesh), axis=1)
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]) & (area2 > eps)
    return Mesh(mesh.vertices, f[ok], mesh.colors)


def compact(mesh: Mesh) -> Mesh:
    """Only the vertices some face uses, renumbered in their old order."""
    used = np.zeros(len(mesh.vertices), dtype=bool)
    used[mesh.faces.reshape(-1)] = True
    new_index = np.cumsum(used) - 1
    return Mesh(mesh.vertices[used], new_index[mesh.faces].astype(np.int32), mesh.colors[used])


def vertex_normals(mesh: Mesh) -> np.ndarray:
    """Area-weighted mean of the adjacent faces' normals, unit length ([0, 0, 0] for a vertex of no face)."""
    f = mesh.faces
    face_n = face_cross(mesh)  # length = 2 area: the weighting
    n = np.zeros((len(mesh.vertices), 3))
    for k in range(3):
        np.add.at(n, f[:, k], face_n)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.maximum(length, 1e-20)).astype(np.float32)


def surface_area(mesh: Mesh) -> float:
    return float(0.5 * np.linalg.norm(face_cross(mesh), axis=1).sum())


def face_cross(mesh: Mesh) -> np.ndarray:
    """[F, 3] float64 cross product of each face's two edges from its first vertex: the face normal, with length
    twice the face's area."""
    v = mesh.vertices.astype(np.float64)
    f = mesh.faces
    return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
