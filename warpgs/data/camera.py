"""One camera: intrinsics, world-to-camera pose, image size and (optional) lens distortion.

Convention (same as COLMAP and gsplat): OpenCV axes, x right, y down, z forward; `viewmat` maps world points
to camera points; pixel (0, 0) is the top-left corner of the image, so the first pixel centre is at (0.5, 0.5).
Distortion is stored as a COLMAP camera model name plus that model's extra parameters (k1, k2, p1, p2, ...),
so pycolmap can project and undistort every model COLMAP knows.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
# Models whose single focal length forces fx == fy.
SINGLE_FOCAL_MODELS = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE",
                       "SIMPLE_FISHEYE", "SIMPLE_DIVISION")
# OpenGL (x right, y up, z backward) <-> OpenCV (x right, y down, z forward): flip the y and z camera axes.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(eq=False)
class Camera:
    K: np.ndarray  # [3, 3] pixels
    viewmat: np.ndarray  # [4, 4] world -> camera
    width: int
    height: int
    name: str = ""  # image file name relative to the scene's image folder
    image_path: Optional[Path] = None
    model: str = "PINHOLE"  # COLMAP camera model name
    distortion: tuple = field(default_factory=tuple)  # the model's extra parameters in COLMAP order

    def __post_init__(self):
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.viewmat = np.asarray(self.viewmat, dtype=np.float64).reshape(4, 4)
        self.width, self.height = int(self.width), int(self.height)
        self.distortion = tuple(float(d) for d in self.distortion)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.name!r}: image size {self.width}x{self.height} must be positive")
        if not (np.all(np.isfinite(self.K)) and np.all(np.isfinite(self.viewmat))):
            raise ValueError(f"camera {self.name!r}: K and viewmat must be finite")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise ValueError(f"camera {self.name!r}: focal lengths must be positive, got {self.K[0, 0]}, {self.K[1, 1]}")
        rot = self.viewmat[:3, :3]
        if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-5) or np.linalg.det(rot) <= 0:
            raise ValueError(f"camera {self.name!r}: viewmat rotation is not a proper rotation")
        if self.model in SINGLE_FOCAL_MODELS and not np.isclose(self.K[0, 0], self.K[1, 1], rtol=1e-6):
            raise ValueError(f"camera {self.name!r}: model {self.model} needs fx == fy, got {self.K[0, 0]}, {self.K[1, 1]}")

    # --- intrinsics and pose -------------------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def camtoworld(self) -> np.ndarray:
        """[4, 4] camera -> world (OpenCV axes)."""
        return invert_rigid(self.viewmat)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        rot, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -rot.T @ t

    @property
    def forward(self) -> np.ndarray:
        """Unit viewing direction (camera +z) in world coordinates."""
        return self.viewmat[2, :3].copy()

    @property
    def has_distortion(self) -> bool:
        return self.model not in PINHOLE_MODELS and any(d != 0.0 for d in self.distortion)

    def viewmat_tensor(self, device=None, dtype=torch.float32) -> torch.Tensor:
        return torch.as_tensor(self.viewmat, dtype=dtype, device=device)

    def K_tensor(self, device=None, dtype=torch.float32) -> torch.Tensor:
        return torch.as_tensor(self.K, dtype=dtype, device=device)

    # --- geometry ------------------------------------------------------------------------------------------
    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return points @ self.viewmat[:3, :3].T + self.viewmat[:3, 3]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [N, 3] -> (pixels [N, 2] including lens distortion, camera z [N]).

        Points at or behind the camera (z <= 0) get NaN pixels.
        """
        cam = self.world_to_camera(points)
        z = cam[:, 2]
        pix = np.full((len(cam), 2), np.nan)
        front = z > 1e-12
        if not self.has_distortion:
            xy = cam[front, :2] / z[front, None]
            pix[front] = xy @ self.K[:2, :2].T + self.K[:2, 2]
        elif front.any():
            pix[front] = self.to_pycolmap().img_from_cam(cam[front], check_cheirality=False)
        return pix, z

    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera seen through an image resized to width x height (intrinsics scale with the image)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, :] *= sx
        K[1, :] *= sy
        return replace(self, K=K, width=width, height=height)

    # --- pycolmap bridge (imported lazily: `import warpgs` needs only warp and torch) -------------------------
    def to_pycolmap(self, camera_id: int = 1):
        import pycolmap

        cam = pycolmap.Camera.create_from_model_name(camera_id, self.model, self.fx, self.width, self.height)
        params = np.array(cam.params, dtype=np.float64)
        focal_idx = list(cam.focal_length_idxs())
        params[focal_idx] = [self.fx] if len(focal_idx) == 1 else [self.fx, self.fy]
        params[list(cam.principal_point_idxs())] = [self.cx, self.cy]
        extra_idx = list(cam.extra_params_idxs())
        if len(self.distortion) not in (0, len(extra_idx)):
            raise ValueError(f"camera {self.name!r}: model {self.model} takes {len(extra_idx)} distortion "
                             f"parameters, got {len(self.distortion)}")
        params[extra_idx] = self.distortion if self.distortion else 0.0
        cam.params = params
        return cam

    @staticmethod
    def from_pycolmap(cam, viewmat: np.ndarray, name: str = "", image_path: Optional[Path] = None) -> "Camera":
        params = np.asarray(cam.params, dtype=np.float64)
        distortion = tuple(params[list(cam.extra_params_idxs())])
        return Camera(K=np.asarray(cam.calibration_matrix()), viewmat=viewmat, width=cam.width, height=cam.height,
                      name=name, image_path=image_path, model=cam.model_name, distortion=distortion)


def optical_axes_focus(cameras: Sequence["Camera"], max_condition: float) -> Optional[np.ndarray]:
    """The least-squares point closest to all cameras' optical axes; None when the axes are (nearly) parallel,
    i.e. the normal equations' condition number exceeds max_condition."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cameras:
        d = cam.forward
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
    if np.linalg.cond(A) > max_condition:
        return None
    return np.linalg.solve(A, b)


def invert_rigid(mat: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform."""
    rot, t = mat[:3, :3], mat[:3, 3]
    out = np.eye(4)
    out[:3, :3] = rot.T
    out[:3, 3] = -rot.T @ t
    return out


def viewmat_from_opengl_camtoworld(c2w_gl: np.ndarray) -> np.ndarray:
    """NeRF/instant-ngp/nerfstudio `transform_matrix` (OpenGL camera -> world) -> OpenCV world -> camera."""
    c2w = np.eye(4)
    c2w[:3, :] = np.asarray(c2w_gl, dtype=np.float64)[:3, :]
    return invert_rigid(c2w @ GL_TO_CV)


def opengl_camtoworld_from_viewmat(viewmat: np.ndarray) -> np.ndarray:
    return invert_rigid(np.asarray(viewmat, dtype=np.float64)) @ GL_TO_CV


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """World -> camera matrix of an OpenCV camera at `eye` looking at `target`, with `up` pointing up in the image."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)  # image right; image down (y) is then z x x
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to `up`")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    view = np.eye(4)
    view[:3, :3] = np.stack([x, y, z])
    view[:3, 3] = -view[:3, :3] @ eye
    return view


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
