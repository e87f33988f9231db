"""How much of the training views a depth prior covers, said once when a run starts that reads it: the share of
pixels with a valid prior and the share at confidence >= 0.5 (where model.prior_points lifts its points beyond 9
views). It describes, it does not decide: on real captures priors valid on 27-97% of the pixels (0-36% at confidence
>= 0.5) helped the sparse preset, and the one that cost it 1 dB (bonsai800 at 12 views, 31% / 7.7%) lies inside that
range (docs/sparse_view.md)."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

CONFIDENT = 0.5


def pixel_shares(valid: np.ndarray, confidence: Optional[np.ndarray]) -> tuple[float, Optional[float]]:
    """(share of pixels in `valid`, share of them at confidence >= CONFIDENT, None without a confidence map)."""
    confident = None if confidence is None else float((valid & (confidence >= CONFIDENT)).mean())
    return float(valid.mean()), confident


def prior_coverage(scene, views: Sequence[int]) -> Optional[dict]:
    """{"views", "valid" (mean share of pixels), "valid_min", "valid_max", "confident" (mean share at confidence
    >= CONFIDENT, None when no prior file carries a confidence)} over `views` that have a prior; None if none does."""
    valid, confident = [], []
    for v in views:
        prior = scene.inv_depth_prior_np(v)
        if prior is None:
            continue
        inv, ok = prior
        share, confident_share = pixel_shares(ok & np.isfinite(inv) & (inv > 0), scene.prior_confidence_np(v))
        valid.append(share)
        if confident_share is not None:
            confident.append(confident_share)
    if not valid:
        return None
    return {"views": len(valid), "valid": float(np.mean(valid)), "valid_min": min(valid), "valid_max": max(valid),
            "confident": float(np.mean(confident)) if confident else None}


def describe_prior_coverage(stats: dict) -> str:
    """One line for the start of a run (prior_coverage's dict)."""
    line = (f"depth priors: valid on {100 * stats['valid']:.0f}% of the pixels of the {stats['views']} training "
            f"views (per view {100 * stats['valid_min']:.0f}-{100 * stats['valid_max']:.0f}%)")
    if stats["confident"] is not None:
        line += f", confidence >= {CONFIDENT:g} on {100 * stats['confident']:.0f}%"
    return line + " (docs/sparse_view.md relates this to what the prior gained on real captures)"
