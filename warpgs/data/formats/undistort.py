"""Undistortion: pycolmap picks the pinhole camera and supplies the lens model; we resample every per-pixel map
(images bilinearly, labels and masks by nearest neighbour) through the same map, so they stay aligned."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
import torch.nn.functional as F

from warpgs.data.camera import Camera


def undistorted_camera(cam: Camera) -> Camera:
    """The pinhole camera COLMAP's undistorter would produce (cropped so that no blank pixels remain)."""
    if not cam.has_distortion:
        return cam
    import pycolmap

    pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), cam.to_pycolmap())
    return replace(cam, K=np.asarray(pinhole.calibration_matrix()), width=pinhole.width, height=pinhole.height,
                   model="PINHOLE", distortion=())


class UndistortMap:
    """Where each pixel centre of the pinhole `target` camera lands in the distorted `source` image.

    The map is computed on first use (one pycolmap projection per target pixel) and shared by all views with
    the same intrinsics.
    """

    def __init__(self, source: Camera, target: Camera):
        self.source, self.target = source, target
        self._source_xy: np.ndarray | None = None

    @staticmethod
    def for_camera(cam: Camera) -> "UndistortMap":
        return UndistortMap(cam, undistorted_camera(cam))

    @property
    def source_xy(self) -> np.ndarray:
        """[H_t, W_t, 2] float32 source-image positions (pixels, corner-origin convention)."""
        if self._source_xy is None:
            t = self.target
            u, v = np.meshgrid(np.arange(t.width) + 0.5, np.arange(t.height) + 0.5)
            rays = np.stack([(u - t.cx) / t.fx, (v - t.cy) / t.fy, np.ones_like(u)], -1)
            src = self.source.to_pycolmap().img_from_cam(rays.reshape(-1, 3), check_cheirality=False)
            self._source_xy = src.reshape(t.height, t.width, 2).astype(np.float32)
        return self._source_xy

    def _grid(self) -> torch.Tensor:
        # grid_sample with align_corners=False puts -1/+1 on the outer pixel edges: the corner-origin convention.
        scale = np.array([2.0 / self.source.width, 2.0 / self.source.height], np.float32)
        return torch.from_numpy(np.nan_to_num(self.source_xy * scale - 1.0, nan=-2.0))[None]

    def coverage(self) -> np.ndarray:
        """[H_t, W_t] bool: target pixels whose source position lies inside the distorted image."""
        x, y = self.source_xy[..., 0], self.source_xy[..., 1]
        return (x >= 0) & (x <= self.source.width) & (y >= 0) & (y <= self.source.height)

    def apply(self, arr: np.ndarray, nearest: bool = False) -> np.ndarray:
        """Resample [H_s, W_s] or [H_s, W_s, C] from the distorted to the undistorted image (same dtype)."""
        if arr.shape[:2] != (self.source.height, self.source.width):
            raise ValueError(f"undistort: map is {arr.shape[1]}x{arr.shape[0]}, the distorted camera is "
                             f"{self.source.width}x{self.source.height}")
        src = torch.from_numpy(np.ascontiguousarray(arr).astype(np.float64 if nearest else np.float32))
        src = src[None, None] if arr.ndim == 2 else src.permute(2, 0, 1)[None]
        grid = self._grid().to(src.dtype)
        out = F.grid_sample(src, grid, mode="nearest" if nearest else "bilinear", padding_mode="border",
                            align_corners=False)[0]
        out = out[0] if arr.ndim == 2 else out.permute(1, 2, 0)
        return out.numpy().astype(arr.dtype)
