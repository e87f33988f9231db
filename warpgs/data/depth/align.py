"""Align a depth prior to SfM points: inverse depth_sfm ~= scale * prior + shift, robust to outliers.

Monocular and video depth models predict inverse depth up to an unknown scale and shift; SfM points give the
metric truth at a few hundred pixels, some of them wrong (bad matches, points seen through a gap). We fit
(scale, shift) in three steps:
1. RANSAC over point pairs (the minimal sample) scored on *relative* residuals, so near and far points count
   alike and a few gross outliers cannot drag the start;
2. least squares on inverse depth over the RANSAC inliers;
3. IRLS with Tukey's biweight (scale from the MAD), which gives gross outliers exactly zero weight.
The residual reported is on inverse depth, over the final inliers, plus its median relative size.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Optional

import numpy as np

from warpgs.data.camera import Camera

TUKEY_C = 4.685  # 95% efficiency under Gaussian noise


@dataclass
class DepthAlignment:
    scale: float
    shift: float
    rms: float  # RMS residual (inverse-depth units) over inliers
    median_relative: float  # median |scale * prior + shift - target| / target over inliers
    n_points: int
    n_inliers: int

    def apply(self, inv_depth: np.ndarray) -> np.ndarray:
        return self.scale * inv_depth + self.shift

    def as_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, (float, np.floating)) else int(v)) for k, v in asdict(self).items()}


def _lstsq(x: np.ndarray, y: np.ndarray, w: Optional[np.ndarray] = None) -> tuple[float, float]:
    A = np.stack([x, np.ones_like(x)], 1)
    if w is not None:
        sw = np.sqrt(w)
        A, y = A * sw[:, None], y * sw
    (s, t), *_ = np.linalg.lstsq(A, y, rcond=None)
    return float(s), float(t)


def _ransac(x: np.ndarray, y: np.ndarray, threshold: float, iters: int, rng: np.random.Generator) -> np.ndarray:
    n = len(x)
    i, j = rng.integers(0, n, size=(2, iters))
    keep = (i != j) & (np.abs(x[i] - x[j]) > 1e-12)
    i, j = i[keep], j[keep]
    if len(i) == 0:
        return np.ones(n, dtype=bool)
    s = (y[i] - y[j]) / (x[i] - x[j])
    t = y[i] - s * x[i]
    # Score all hypotheses at once: [iters, n] relative residuals (chunked to bound memory).
    best, best_count = None, -1
    for start in range(0, len(s), 256):
        res = np.abs(s[start:start + 256, None] * x[None] + t[start:start + 256, None] - y[None]) / np.abs(y[None])
        counts = (res < threshold).sum(1)
        k = int(counts.argmax())
        if counts[k] > best_count:
            best_count, best = int(counts[k]), res[k] < threshold
    return best


def align_inverse_depth(prior: np.ndarray, target: np.ndarray, *, ransac_iters: int = 500,
                        ransac_threshold: float = 0.05, irls_iters: int = 30, seed: int = 0) -> DepthAlignment:
    """Fit target ~= scale * prior + shift (both inverse depths, 1-D arrays of matched samples)."""
    x = np.asarray(prior, dtype=np.float64).ravel()
    y = np.asarray(target, dtype=np.float64).ravel()
    ok = np.isfinite(x) & np.isfinite(y) & (y > 0)
    x, y = x[ok], y[ok]
    if len(x) < 3:
        raise ValueError(f"depth alignment needs at least 3 points with valid prior and depth, got {len(x)}")
    if np.ptp(x) <= 1e-12:
        raise ValueError("depth alignment: the prior is constant at the points, so its scale is undetermined")
    inliers = _ransac(x, y, ransac_threshold, ransac_iters, np.random.default_rng(seed))
    if inliers.sum() < 3:
        inliers = np.ones(len(x), dtype=bool)
    s, t = _lstsq(x[inliers], y[inliers])
    w = inliers.astype(np.float64)
    for _ in range(irls_iters):
        r = s * x + t - y
        sigma = 1.4826 * np.median(np.abs(r[w > 0])) + 1e-12
        u = r / (TUKEY_C * sigma)
        w_new = np.where(np.abs(u) < 1, (1 - u ** 2) ** 2, 0.0)
        if (w_new > 0).sum() < 3:
            break
        s_new, t_new = _lstsq(x, y, w_new)
        converged = abs(s_new - s) <= 1e-10 * abs(s) + 1e-15 and abs(t_new - t) <= 1e-10 * (abs(t) + abs(s))
        s, t, w = s_new, t_new, w_new
        if converged:
            break
    final = w > 0
    r = s * x[final] + t - y[final]
    return DepthAlignment(scale=s, shift=t, rms=float(np.sqrt(np.mean(r ** 2))),
                          median_relative=float(np.median(np.abs(r) / y[final])), n_points=len(x),
                          n_inliers=int(final.sum()))


def sample_bilinear(image: np.ndarray, valid: np.ndarray, pix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of [H, W] `image` at pixel positions [N, 2] (corner-origin convention); a sample is
    valid only when all four neighbours are."""
    h, w = image.shape
    x, y = pix[:, 0] - 0.5, pix[:, 1] - 0.5  # to pixel-centre coordinates
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h) & np.isfinite(x) & np.isfinite(y)
    x0c, y0c = np.clip(x0, 0, w - 2), np.clip(y0, 0, h - 2)
    fx, fy = x - x0c, y - y0c
    corners = [(y0c, x0c, (1 - fx) * (1 - fy)), (y0c, x0c + 1, fx * (1 - fy)),
               (y0c + 1, x0c, (1 - fx) * fy), (y0c + 1, x0c + 1, fx * fy)]
    value = sum(image[r, c] * wgt for r, c, wgt in corners)
    ok = inside.copy()
    for r, c, _ in corners:
        ok &= valid[r, c]
    return value, ok


def align_depth_to_points(inv_prior: np.ndarray, valid: np.ndarray, camera: Camera, points: np.ndarray,
                          **kwargs) -> DepthAlignment:
    """Align an inverse-depth prior [H, W] of `camera`'s view to the world points it sees ([N, 3])."""
    if inv_prior.shape != (camera.height, camera.width):
        raise ValueError(f"prior is {inv_prior.shape[::-1]} but camera {camera.name!r} is "
                         f"{camera.width}x{camera.height}")
    pix, z = camera.project(points)
    front = z > 0
    values, ok = sample_bilinear(inv_prior, valid, pix[front])
    return align_inverse_depth(values[ok], 1.0 / z[front][ok], **kwargs)
