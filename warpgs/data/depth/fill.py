"""Fill the pixels a depth prior left invalid from its valid ones (issue 15: on 3-view captures the plane sweep
keeps ~64 % of the pixels; the rest are mostly textureless walls and floor, where the photometric loss constrains
geometry least and a prior would help most).

The fill is a harmonic interpolation of *inverse* depth: the inverse depth of a plane is an affine function of the
pixel coordinates, and affine functions are harmonic, so a textureless planar region bounded by valid pixels is
filled with its plane. It runs coarse to fine (a push-pull pyramid, then Jacobi sweeps of the 4-neighbour average
at every level, so large holes converge in a few hundred cheap sweeps) and is edge-aware: a neighbour's weight
falls with its colour difference, so a fill does not flow across an image edge as readily as along a surface.
Only invalid pixels change; the caller gives the filled ones a low confidence (they are interpolated, not seen).
Torch on the CPU or GPU; no Warp.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

DEFAULT_SWEEPS = 60  # Jacobi sweeps per pyramid level
DEFAULT_SIGMA_COLOR = 0.1  # colour difference (RGB in [0, 1], Euclidean) at which a neighbour's weight is e^-1/2
# Least neighbour weight: across the strongest edge the fill still flows a little, so no pixel is ever cut off
# from every neighbour (an isolated pixel would keep an arbitrary value) and the values stay within the valid range.
MIN_WEIGHT = 1e-3


def _down(x: torch.Tensor) -> torch.Tensor:
    """2x2 mean of [1, C, H, W], keeping the odd last row/column (ceil)."""
    return F.avg_pool2d(x, 2, stride=2, ceil_mode=True)


def _edge_weights(image: torch.Tensor, sigma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights of the right and lower neighbour of each pixel ([1, 1, H, W-1] and [1, 1, H-1, W])."""
    dx = (image[..., :, 1:] - image[..., :, :-1]).pow(2).sum(1, keepdim=True)
    dy = (image[..., 1:, :] - image[..., :-1, :]).pow(2).sum(1, keepdim=True)
    return (torch.exp(-dx / (2 * sigma ** 2)).clamp_min(MIN_WEIGHT),
            torch.exp(-dy / (2 * sigma ** 2)).clamp_min(MIN_WEIGHT))


def _jacobi(value: torch.Tensor, fixed: torch.Tensor, wx: torch.Tensor, wy: torch.Tensor, sweeps: int) -> torch.Tensor:
    """Sweeps of the weighted 4-neighbour average on the pixels that are not fixed."""
    # Each pixel's total neighbour weight is the same every sweep.
    total = F.pad(wx, (1, 0)) + F.pad(wx, (0, 1)) + F.pad(wy, (0, 0, 1, 0)) + F.pad(wy, (0, 0, 0, 1))
    total = total.clamp_min(1e-12)  # only a 1x1 level has no neighbours, and it is never a hole
    for _ in range(sweeps):
        acc = (F.pad(wx * value[..., :, 1:], (0, 1)) + F.pad(wx * value[..., :, :-1], (1, 0))
               + F.pad(wy * value[..., 1:, :], (0, 0, 0, 1)) + F.pad(wy * value[..., :-1, :], (0, 0, 1, 0)))
        value = torch.where(fixed, value, acc / total)
    return value


def fill_inverse_depth(inv_depth: np.ndarray, valid: np.ndarray, image: np.ndarray, *,
                       sweeps: int = DEFAULT_SWEEPS, sigma_color: float = DEFAULT_SIGMA_COLOR,
                       device=None) -> tuple[np.ndarray, np.ndarray]:
    """(inverse depth [H, W] with the invalid pixels filled, filled-pixel mask [H, W] bool: every invalid pixel
    whose fill is positive, i.e. all of them when the valid values are, as fills are weighted means of those).

    inv_depth: [H, W], values at valid pixels (others ignored); valid: [H, W] bool; image: [H, W, 3] in [0, 1],
    the view the prior belongs to (its edges stop the fill). With no valid pixel there is nothing to fill from:
    the input comes back unchanged with an empty mask."""
    inv_depth, valid, image = np.asarray(inv_depth), np.asarray(valid, dtype=bool), np.asarray(image)
    if inv_depth.shape != valid.shape or image.shape[:2] != valid.shape or image.ndim != 3:
        raise ValueError(f"fill_inverse_depth: inverse depth {inv_depth.shape}, valid {valid.shape} and image "
                         f"{image.shape} must share [H, W] (image [H, W, 3])")
    if sweeps < 0 or sigma_color <= 0:
        raise ValueError(f"fill_inverse_depth: sweeps must be >= 0 and sigma_color > 0, got {sweeps}, {sigma_color}")
    if not valid.any() or valid.all():
        return inv_depth.copy(), np.zeros_like(valid)
    dev = torch.device(device or "cpu")
    value = torch.as_tensor(np.where(valid, inv_depth, 0.0), dtype=torch.float64, device=dev)[None, None]
    weight = torch.as_tensor(valid, dtype=torch.float64, device=dev)[None, None]
    img = torch.as_tensor(image[..., :3], dtype=torch.float64, device=dev).permute(2, 0, 1)[None]

    # Push: weighted means down to a level every pixel of which has support (or 1x1).
    levels = [(value, weight, img)]
    while levels[-1][1].min() == 0 and min(levels[-1][0].shape[-2:]) > 1:
        v, w, im = levels[-1]
        sw = _down(w)
        sv = _down(v * w)
        levels.append((torch.where(sw > 0, sv / sw.clamp_min(1e-12), 0.0), (sw > 0).to(w.dtype), _down(im)))
    # Pull: from the coarsest level up, holes start from the level below's answer and relax edge-aware.
    filled = levels[-1][0]
    for v, w, im in reversed(levels):
        if filled.shape != v.shape:
            filled = F.interpolate(filled, size=v.shape[-2:], mode="bilinear", align_corners=False)
        fixed = w > 0
        wx, wy = _edge_weights(im, sigma_color)
        filled = _jacobi(torch.where(fixed, v, filled), fixed, wx, wy, sweeps)
    out = filled[0, 0].cpu().numpy().astype(inv_depth.dtype, copy=False)
    filled_mask = ~valid & (out > 0)  # a fill never puts a point behind the camera
    return np.where(filled_mask, out, inv_depth), filled_mask
