"""Exact depth maps of analytic surfaces (a sphere, a plane square) from a ring of inward-looking cameras, for
the TSDF fusion tests and the mesh benchmark."""
from __future__ import annotations

import numpy as np

from warpgs.data.camera import intrinsics_matrix, look_at

WIDTH, HEIGHT, FOCAL = 64, 48, 60.0


def ring_cameras(target, distance: float, elevations=(-30.0, 10.0, 45.0), n_azimuth: int = 12):
    """(K, viewmat) of cameras on rings around `target`, looking at it."""
    K = intrinsics_matrix(FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2)
    target = np.asarray(target, dtype=np.float64)
    views = []
    for el in np.radians(elevations):
        for az in 2 * np.pi * np.arange(n_azimuth) / n_azimuth:
            eye = target + distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            views.append((K, look_at(eye, target)))
    return views


def _rays(K, viewmat):
    """World ray origin (the camera centre) and directions with unit camera z, per pixel [H, W, 3]."""
    u, v = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    return -R.T @ t, d_cam @ R  # row vectors: d_world = R^T d_cam


def sphere_depth(K, viewmat, centre, radius) -> np.ndarray:
    """Camera z of the nearer hit of each pixel-centre ray (inf on a miss)."""
    o, d = _rays(K, viewmat)
    oc = o - np.asarray(centre, dtype=np.float64)
    a, b, c = (d * d).sum(-1), 2.0 * d @ oc, oc @ oc - radius ** 2
    disc = b * b - 4 * a * c
    z = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a)  # camera z, since d has unit z
    return np.where(disc >= 0, z, np.inf).astype(np.float32)


def square_depth(K, viewmat, height: float, half: float) -> np.ndarray:
    """Camera z where each ray meets the square |x|, |y| <= half at z = height, seen from above (inf elsewhere)."""
    o, d = _rays(K, viewmat)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (height - o[2]) / d[..., 2]
    p = o + z[..., None] * d
    hit = (z > 0) & (np.abs(p[..., 0]) <= half) & (np.abs(p[..., 1]) <= half)
    return np.where(hit, z, np.inf).astype(np.float32)
