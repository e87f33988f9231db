"""Standard depth-accuracy metrics (AbsRel, SqRel, RMSE, delta < 1.25) over the pixels where both are known."""
from __future__ import annotations

from typing import Optional

import numpy as np


def depth_metrics(pred_depth: np.ndarray, gt_depth: np.ndarray, valid: Optional[np.ndarray] = None) -> dict:
    """Metrics of predicted vs reference depth; pixels count when both are finite and positive (and `valid`).

    Returns abs_rel = mean |p - g| / g, sq_rel = mean (p - g)^2 / g, rmse, delta_1_25 = fraction with
    max(p / g, g / p) < 1.25, and n (pixels evaluated).
    """
    p = np.asarray(pred_depth, dtype=np.float64)
    g = np.asarray(gt_depth, dtype=np.float64)
    if p.shape != g.shape:
        raise ValueError(f"prediction {p.shape} and reference {g.shape} differ in shape")
    use = np.isfinite(p) & np.isfinite(g) & (p > 0) & (g > 0)
    if valid is not None:
        use &= np.asarray(valid, dtype=bool)
    n = int(use.sum())
    if n == 0:
        return {"abs_rel": float("nan"), "sq_rel": float("nan"), "rmse": float("nan"), "delta_1_25": float("nan"),
                "n": 0}
    p, g = p[use], g[use]
    ratio = np.maximum(p / g, g / p)
    return {"abs_rel": float(np.mean(np.abs(p - g) / g)), "sq_rel": float(np.mean((p - g) ** 2 / g)),
            "rmse": float(np.sqrt(np.mean((p - g) ** 2))), "delta_1_25": float(np.mean(ratio < 1.25)), "n": n}


def point_depth_metrics(inv_depth: np.ndarray, valid: np.ndarray, pix: np.ndarray, z: np.ndarray,
                        confidence: Optional[np.ndarray] = None, keep: tuple = (0.25, 0.5, 1.0)) -> dict:
    """Score an inverse-depth map [H, W] against sparse reference depths z [M] at pixel positions pix [M, 2]
    (corner-origin; each point reads the pixel it falls in).

    Returns depth_metrics over the reference points on valid pixels, plus point_coverage (the share of reference
    points on valid pixels) and, with a confidence map: the confidence-weighted AbsRel (what a loss weighted by it
    sees) and "top": the metrics of the most confident `keep` fractions of those points (a confidence that ranks
    errors well makes AbsRel fall as the fraction shrinks)."""
    h, w = inv_depth.shape
    col = np.clip(np.floor(pix[:, 0]).astype(np.int64), 0, w - 1)
    row = np.clip(np.floor(pix[:, 1]).astype(np.int64), 0, h - 1)
    inv = inv_depth[row, col].astype(np.float64)
    ok = valid[row, col] & np.isfinite(inv) & (inv > 0)
    pred = np.where(ok, 1.0 / np.where(ok, inv, 1.0), np.nan)
    out = depth_metrics(pred, z, ok)
    out["point_coverage"] = float(ok.mean()) if len(ok) else float("nan")
    if confidence is None or not ok.any():
        return out
    c = confidence[row, col][ok].astype(np.float64)
    rel = np.abs(pred[ok] - z[ok]) / z[ok]
    out["abs_rel_weighted"] = float((c * rel).sum() / max(c.sum(), 1e-12))
    order = np.argsort(-c, kind="stable")
    out["top"] = {}
    for frac in keep:
        sel = np.zeros(len(c), dtype=bool)
        sel[order[:max(1, int(round(frac * len(c))))]] = True
        m = depth_metrics(pred[ok][sel], z[ok][sel])
        out["top"][f"{frac:g}"] = {"abs_rel": m["abs_rel"], "delta_1_25": m["delta_1_25"], "n": m["n"]}
    return out
