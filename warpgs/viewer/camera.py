"""Viewer cameras -> warpgs cameras, and where the viewer starts. Numpy only (no viser, no torch).

viser reports a browser's camera as `wxyz` + `position` (P_world = R p_camera + t) in OpenCV axes (x right, y down,
z forward: the same as ours), a vertical field of view in radians and the canvas size in pixels. The rendered image
is stretched over the whole canvas, so the focal lengths follow the canvas's fields of view: fy from the vertical
one, fx from the horizontal one the canvas's aspect implies (they differ only by the rounding of a scaled-down
image size). The principal point is the image centre (W/2, H/2 with pixel centres at +0.5).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

from warpgs.data.camera import invert_rigid

DEFAULT_FOV = math.radians(60.0)  # the start pose when no training camera says otherwise


@dataclass(frozen=True)
class ViewerCamera:
    """One browser camera: camera-to-world [4, 4] (OpenCV axes), vertical fov (radians), canvas size (pixels)."""

    c2w: np.ndarray
    fov: float
    width: int
    height: int

    @staticmethod
    def from_wxyz(wxyz, position, fov: float, width: int, height: int) -> "ViewerCamera":
        c2w = np.eye(4)
        c2w[:3, :3] = quat_to_matrix(wxyz)
        c2w[:3, 3] = np.asarray(position, dtype=np.float64).reshape(3)
        return ViewerCamera(c2w, float(fov), int(width), int(height))


def quat_to_matrix(wxyz) -> np.ndarray:
    """Rotation matrix of a quaternion (w, x, y, z), normalised first."""
    q = np.asarray(wxyz, dtype=np.float64).reshape(-1)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-12:
        raise ValueError(f"wxyz: expected a finite non-zero quaternion (w, x, y, z), got {wxyz!r}")
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def fit_size(width: int, height: int, max_side: Optional[int]) -> Tuple[int, int]:
    """The canvas size scaled down (never up) so its longer side is at most max_side (None or 0: as it is)."""
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise ValueError(f"canvas size: expected positive width and height, got {width}x{height}")
    if not max_side or max(width, height) <= max_side:
        return width, height
    s = max_side / max(width, height)
    return max(1, round(width * s)), max(1, round(height * s))


def to_warpgs(cam: ViewerCamera, width: int, height: int) -> Tuple[np.ndarray, np.ndarray]:
    """(viewmat [4, 4] world -> camera, K [3, 3]) for an image of width x height stretched over cam's canvas."""
    c2w = np.asarray(cam.c2w, dtype=np.float64)
    if c2w.shape == (3, 4):
        c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
    if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
        raise ValueError(f"c2w: expected a finite [4, 4] camera-to-world matrix, got shape {c2w.shape}")
    rot = c2w[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-5) or np.linalg.det(rot) <= 0:
        raise ValueError("c2w: the rotation part is not a proper rotation")
    if not (math.isfinite(cam.fov) and 0.0 < cam.fov < math.pi):
        raise ValueError(f"fov: expected a vertical field of view in (0, pi) radians, got {cam.fov!r}")
    if cam.width <= 0 or cam.height <= 0 or width <= 0 or height <= 0:
        raise ValueError(f"image size: expected positive sizes, got canvas {cam.width}x{cam.height}, "
                         f"image {width}x{height}")
    tan_y = math.tan(cam.fov / 2.0)
    tan_x = tan_y * cam.width / cam.height
    K = np.array([[width / (2.0 * tan_x), 0.0, width / 2.0],
                  [0.0, height / (2.0 * tan_y), height / 2.0],
                  [0.0, 0.0, 1.0]])
    return invert_rigid(c2w), K


@dataclass(frozen=True)
class StartPose:
    """Where a new browser's camera starts: position, look-at point, up vector (world), vertical fov."""

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    fov: float


def scene_up(cameras: Sequence) -> Optional[np.ndarray]:
    """The cameras' mean image-up direction in world coordinates (image down is camera +y), or None."""
    if not cameras:
        return None
    up = -np.mean([np.asarray(c.viewmat)[1, :3] for c in cameras], 0)
    n = np.linalg.norm(up)
    return up / n if n > 1e-9 else None


def pose_of_camera(cam, means: Optional[np.ndarray] = None) -> StartPose:
    """A training camera's pose; it looks at the median depth of the points in front of it (1 without any)."""
    viewmat = np.asarray(cam.viewmat, dtype=np.float64)
    center, forward, up = -viewmat[:3, :3].T @ viewmat[:3, 3], viewmat[2, :3], -viewmat[1, :3]
    depth = 1.0
    if means is not None and len(means):
        z = (np.asarray(means, np.float64) - center) @ forward
        z = z[z > 1e-6]
        if len(z):
            depth = float(np.median(z))
    fov = 2.0 * math.atan(cam.height / (2.0 * float(np.asarray(cam.K)[1, 1])))
    return StartPose(center, center + depth * forward, up, fov)


def pose_around(means: Optional[np.ndarray], fov: float = DEFAULT_FOV) -> StartPose:
    """No cameras: look at the points' median from outside most of them. Up is -y, COLMAP's habit (its world
    frame often starts as the first camera's, whose image down is +y); the camera looks along +z like that one."""
    up = np.array([0.0, -1.0, 0.0])
    if means is None or not len(means):
        center, radius = np.zeros(3), 1.0
    else:
        means = np.asarray(means, np.float64)
        means = means[np.all(np.isfinite(means), 1)]
        center = np.median(means, 0) if len(means) else np.zeros(3)
        dist = np.linalg.norm(means - center, axis=1) if len(means) else np.ones(1)
        radius = float(np.quantile(dist, 0.8)) or 1.0
    distance = radius / math.tan(fov / 2.0) * 1.2  # the central 80 % fills most of the view
    direction = np.array([0.0, 0.3, 1.0]) / math.hypot(0.3, 1.0)  # along +z, tilted down (+y is down)
    return StartPose(center - distance * direction, center, up, fov)
