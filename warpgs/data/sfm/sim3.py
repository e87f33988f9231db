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


def orientation_alignment(estimated: Sequence[Camera], reference: Sequence[Camera]) -> np.ndarray:
    """The world rotation Q (estimated frame -> reference frame) that best maps the cameras' orientations,
    R_est ~= R_ref Q for every camera: the chordal mean of R_ref^T R_est, refined once on the cameras within 10
    degrees of it so that a few wrong poses do not pull it. Unlike aligning the centres, it is well posed when the
    centres lie on a line or in a plane (a video sweep)."""
    def mean_rotation(parts):
        U, _, Vt = np.linalg.svd(sum(parts))
        return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt

    parts = [np.asarray(r.viewmat, np.float64)[:3, :3].T @ np.asarray(e.viewmat, np.float64)[:3, :3]
             for e, r in zip(estimated, reference)]
    Q = mean_rotation(parts)
    close = [p for p in parts if rotation_angle_deg(p @ Q.T) < 10.0]
    return mean_rotation(close) if close else Q


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """The angle of a rotation matrix, in degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0))))


def pose_errors(estimated: Sequence[Camera], reference: Sequence[Camera], align: str = "centres") -> dict:
    """Align `estimated` cameras to `reference` by a similarity, then compare every pose.

    align: "centres" (Umeyama on the camera centres; needs centres spread in 3D, as an orbit) or "orientations"
    (the rotation from the cameras' orientations, orientation_alignment, then scale and shift from the centres).
    Returns rotation errors (degrees), centre errors (reference units) and the fitted scale, as
    {"rotation_deg": [..], "center": [..], "max_rotation_deg", "max_center", "scale"}.
    """
    if len(estimated) != len(reference):
        raise ValueError("pose_errors: camera lists differ in length")
    if align not in ("centres", "orientations"):
        raise ValueError(f"pose_errors: align must be 'centres' or 'orientations', got {align!r}")
    src = np.stack([c.center for c in estimated])
    dst = np.stack([c.center for c in reference])
    if align == "centres":
        s, R, t = umeyama(src, dst)
    else:
        R = orientation_alignment(estimated, reference)  # also maps estimated world points to the reference world
        xs, xd = (src - src.mean(0)) @ R.T, dst - dst.mean(0)
        s = float((xs * xd).sum() / max((xs * xs).sum(), 1e-300))
        t = dst.mean(0) - s * R @ src.mean(0)
    rot_err, centre_err = [], []
    for est, ref in zip(estimated, reference):
        centre = s * R @ est.center + t
        # A world rotation R maps est's world to ref's world: R_cam,aligned = R_cam,est R^T.
        rot_err.append(rotation_angle_deg((est.viewmat[:3, :3] @ R.T) @ ref.viewmat[:3, :3].T))
        centre_err.append(float(np.linalg.norm(centre - ref.center)))
    return {"rotation_deg": rot_err, "center": centre_err, "max_rotation_deg": max(rot_err),
            "max_center": max(centre_err), "scale": s}
