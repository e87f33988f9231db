"""Resizing per-pixel maps for downscale factors: area averaging for colours and depth, centre sampling for ids."""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

DOWNSCALE_FACTORS = (1, 2, 4, 8)


def scaled_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """An image's size at 1/factor: round(W/factor) x round(H/factor), at least 1 px."""
    return max(1, round(width / factor)), max(1, round(height / factor))


def downscaled_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """scaled_size for the downscale factors a scene folder can be read at."""
    if factor not in DOWNSCALE_FACTORS:
        raise ValueError(f"downscale factor must be one of {DOWNSCALE_FACTORS}, got {factor}")
    return scaled_size(width, height, factor)


def resize_tensor(t: torch.Tensor, width: int, height: int, mode: str) -> torch.Tensor:
    """[H, W] or [H, W, C] tensor (on any device) -> the same at (height, width). mode "area" (the mean of each
    output pixel's footprint) or "bilinear" compute in float32 and return the input's dtype; "nearest" takes the
    source pixel under each output pixel's centre (resize_nearest's rule; never blends flags or ids)."""
    x = (t[..., None] if t.dim() == 2 else t).permute(2, 0, 1)[None]
    if mode == "nearest":
        rows = torch.from_numpy(nearest_sources(height, x.shape[2])).to(x.device)
        cols = torch.from_numpy(nearest_sources(width, x.shape[3])).to(x.device)
        x = x[:, :, rows][:, :, :, cols]
    else:
        align = False if mode == "bilinear" else None
        x = F.interpolate(x.float(), size=(height, width), mode=mode, align_corners=align).to(t.dtype)
    out = x[0].permute(1, 2, 0).contiguous()
    return out[..., 0] if t.dim() == 2 else out


def resize_area(arr: np.ndarray, width: int, height: int) -> np.ndarray:
    """[H, W] or [H, W, C] float -> same rank at (height, width), each output pixel the mean of its footprint."""
    if arr.shape[1] == width and arr.shape[0] == height:
        return arr
    return resize_tensor(torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float32)), width, height, "area").numpy()


def resize_bilinear(arr: np.ndarray, width: int, height: int) -> np.ndarray:
    """Upsampling of smooth maps (a prior computed at a coarser scale)."""
    return resize_tensor(torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float32)), width, height,
                         "bilinear").numpy()


def nearest_sources(size: int, source_size: int) -> np.ndarray:
    """For each of `size` output pixels along an axis, the source pixel under its centre (of `source_size`)."""
    return np.minimum(((np.arange(size) + 0.5) * source_size / size).astype(np.int64), source_size - 1)


def resize_nearest(arr: np.ndarray, width: int, height: int) -> np.ndarray:
    """Label maps and other ids: take the source pixel under each output pixel's centre (never blends ids)."""
    h, w = arr.shape[:2]
    return arr[nearest_sources(height, h)[:, None], nearest_sources(width, w)[None, :]]


def resize_masked(values: np.ndarray, valid: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Area-average only the valid pixels; an output pixel is valid when at least half its footprint was."""
    if values.shape[1] == width and values.shape[0] == height:
        return values, valid
    weight = valid.astype(np.float32)
    total = resize_area(np.where(valid, values, 0.0).astype(np.float32), width, height)
    coverage = resize_area(weight, width, height)
    out_valid = coverage >= 0.5
    out = np.where(out_valid, total / np.maximum(coverage, 1e-12), 0.0).astype(np.float32)
    return out, out_valid
