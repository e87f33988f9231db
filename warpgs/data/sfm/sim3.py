"""Similarity alignment of camera sets (SfM recovers poses only up to scale, rotation and translation)."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from warpgs.data.camera import Camera


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares (s, R, t) with dst ~= s R src + t for matched points [N, 3] (Umeyama 1991)."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama: need matched [N>=3, 3] point sets, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var_s) if with_scale else 1.0
    return s, R, mu_d - s * R @ mu_s


def pose_errors(estimated: Sequence[Camera], reference: Sequence[Camera]) -> dict:
    """Align `estimated` camera centres to `reference` by a similarity, then compare every pose.

    Returns rotation errors (degrees), centre errors (reference units) and the fitted scale, as
    {"rotation_deg": [..], "center": [..], "max_rotation_deg", "max_center", "scale"}.
    """
    if len(estimated) != len(reference):
        raise ValueError("pose_errors: camera lists differ in length")
    s, R, t = umeyama(np.stack([c.center for c in estimated]), np.stack([c.center for c in reference]))
    rot_err, centre_err = [], []
    for est, ref in zip(estimated, reference):
        centre = s * R @ est.center + t
        # A world rotation R maps est's world to ref's world: R_cam,aligned = R_cam,est R^T.
        rel = (est.viewmat[:3, :3] @ R.T) @ ref.viewmat[:3, :3].T
        angle = np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0)))
        rot_err.append(float(angle))
        centre_err.append(float(np.linalg.norm(centre - ref.center)))
    return {"rotation_deg": rot_err, "center": centre_err, "max_rotation_deg": max(rot_err),
            "max_center": max(centre_err), "scale": s}
