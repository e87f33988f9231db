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
