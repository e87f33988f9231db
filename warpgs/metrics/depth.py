"""Geometry metrics of the sparse-view study: the relative-depth judgement (the paper's psychophysics, automated),
AbsRel of rendered depth, and the primitive count.

Relative-depth judgement. The paper's observers were shown two probe points and asked which is closer. Here:
draw random pixel pairs among the pixels with a known, finite reference depth, keep the pairs whose reference
depths differ by more than `margin` (relative: |g1 - g2| / min(g1, g2) > margin, so the answer is not a
coin flip at the reference's own precision), optionally only pairs at most `max_distance` pixels apart, and
score the fraction whose rendered depth order matches the reference order. A rendered tie scores 1/2 (chance).
A pixel where nothing was rendered (alpha below `min_alpha`, or a non-finite / non-positive depth) reads as
infinitely far, as an observer would read an empty pixel; sky in the reference (+inf) is not probed.
Perfect depth scores 1.0, any order-reversing depth (e.g. 1 / depth) 0.0, a constant map 0.5.

AbsRel: mean |d̂ - d| / d over pixels with a finite positive reference and a rendered surface (alpha >=
min_alpha); `coverage` says what fraction of the reference pixels that is, so holes do not hide.

Pure torch on [H, W] / [H, W, 1] maps; `evaluate_depth` renders views through a callable.
"""
from __future__ import annotations

import math
from typing import Callable, Optional, Sequence

import torch

DEFAULT_PAIRS = 2000
DEFAULT_MARGIN = 0.05
DEFAULT_MIN_ALPHA = 0.5


def _flat(x: torch.Tensor, name: str) -> torch.Tensor:
    if x.dim() == 3 and x.shape[-1] == 1:
        x = x[..., 0]
    if x.dim() != 2:
        raise ValueError(f"{name}: expected [H, W] or [H, W, 1], got {list(x.shape)}")
    return x


def reference_valid(gt_depth: torch.Tensor, valid: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Pixels with a finite, positive reference depth (and `valid`)."""
    ok = torch.isfinite(gt_depth) & (gt_depth > 0)
    if valid is not None:
        ok &= _flat(valid, "valid").to(device=gt_depth.device, dtype=torch.bool)
    return ok


def rendered_surface(pred_depth: torch.Tensor, alpha: Optional[torch.Tensor] = None,
                     min_alpha: float = DEFAULT_MIN_ALPHA) -> torch.Tensor:
    """Pixels where the render shows a surface: finite positive depth and alpha >= min_alpha."""
    ok = torch.isfinite(pred_depth) & (pred_depth > 0)
    if alpha is not None:
        ok &= _flat(alpha, "alpha").to(pred_depth.device) >= min_alpha
    return ok


def sample_pairs(gt_depth: torch.Tensor, valid: torch.Tensor, num_pairs: int = DEFAULT_PAIRS,
                 margin: float = DEFAULT_MARGIN, max_distance: Optional[float] = None,
                 generator: Optional[torch.Generator] = None, max_rounds: int = 50) -> torch.Tensor:
    """[P, 2] flat pixel indices of up to `num_pairs` pairs of valid pixels whose reference depths differ by
    more than `margin` (relative), at most `max_distance` pixels apart when given. Fewer pairs come back when
    the image has too few such pairs (e.g. a flat wall)."""
    H, W = gt_depth.shape
    cand = torch.nonzero(valid.reshape(-1).cpu(), as_tuple=False)[:, 0]
    if len(cand) < 2 or num_pairs <= 0:
        return torch.zeros(0, 2, dtype=torch.long)
    g = gt_depth.reshape(-1).detach().double().cpu()
    lo, hi = float(g[cand].min()), float(g[cand].max())
    if hi - lo <= margin * lo:  # no pair of valid pixels can differ by more than the margin
        return torch.zeros(0, 2, dtype=torch.long)
    gen = generator if generator is not None else torch.Generator().manual_seed(0)
    picked, have = [], 0
    for _ in range(max_rounds):
        n = max(4 * (num_pairs - have), 256)
        a = cand[torch.randint(len(cand), (n,), generator=gen)]
        if max_distance is None:
            b = cand[torch.randint(len(cand), (n,), generator=gen)]
        else:  # a random offset within the disc, then keep it if it lands on a valid pixel
            r = float(max_distance) * torch.rand(n, generator=gen, dtype=torch.float64).sqrt()
            t = 2 * math.pi * torch.rand(n, generator=gen, dtype=torch.float64)
            ya = torch.div(a, W, rounding_mode="floor")
            yb = (ya + (r * torch.sin(t)).round().long())
            xb = (a % W + (r * torch.cos(t)).round().long())
            inside = (yb >= 0) & (yb < H) & (xb >= 0) & (xb < W)
            b = torch.where(inside, yb.clamp(0, H - 1) * W + xb.clamp(0, W - 1), a)
            on = valid.reshape(-1).cpu()[b] & inside
            a, b = a[on], b[on]
        ga, gb = g[a], g[b]
        keep = (a != b) & ((ga - gb).abs() > margin * torch.minimum(ga, gb))
        a, b = a[keep], b[keep]
        take = min(len(a), num_pairs - have)
        picked.append(torch.stack([a[:take], b[:take]], 1))
        have += take
        if have >= num_pairs:
            break
    return torch.cat(picked) if picked else torch.zeros(0, 2, dtype=torch.long)


def depth_order_accuracy(pred_depth: torch.Tensor, gt_depth: torch.Tensor, *, alpha: Optional[torch.Tensor] = None,
                         valid: Optional[torch.Tensor] = None, num_pairs: int = DEFAULT_PAIRS,
                         margin: float = DEFAULT_MARGIN, max_distance: Optional[float] = None,
                         min_alpha: float = DEFAULT_MIN_ALPHA, seed: int = 0) -> dict:
    """{"accuracy", "pairs"}: the fraction of probe pairs whose rendered order matches the reference (NaN when
    no pair qualifies), and how many pairs were judged. Deterministic for a given seed."""
    pred, gt = _flat(pred_depth, "pred_depth").detach(), _flat(gt_depth, "gt_depth").detach()
    if pred.shape != gt.shape:
        raise ValueError(f"pred_depth {list(pred.shape)} and gt_depth {list(gt.shape)} differ in shape")
    if not margin >= 0:
        raise ValueError(f"margin: expected >= 0, got {margin}")
    pairs = sample_pairs(gt, reference_valid(gt, valid), num_pairs, margin, max_distance,
                         torch.Generator().manual_seed(int(seed)))
    if len(pairs) == 0:
        return {"accuracy": float("nan"), "pairs": 0}
    surface = rendered_surface(pred, alpha, min_alpha)
    p = torch.where(surface, pred.double(), torch.full_like(pred, float("inf"), dtype=torch.float64)).reshape(-1).cpu()
    g = gt.double().reshape(-1).cpu()
    a, b = pairs[:, 0], pairs[:, 1]
    truth = torch.sign(g[a] - g[b])
    pa, pb = p[a], p[b]
    both_inf = torch.isinf(pa) & torch.isinf(pb)
    said = torch.where(both_inf, torch.zeros_like(pa), torch.sign(pa - pb))
    score = torch.where(said == 0, torch.full_like(pa, 0.5), (said == truth).double())
    return {"accuracy": float(score.mean()), "pairs": int(len(pairs))}


def abs_rel(pred_depth: torch.Tensor, gt_depth: torch.Tensor, *, alpha: Optional[torch.Tensor] = None,
            valid: Optional[torch.Tensor] = None, min_alpha: float = DEFAULT_MIN_ALPHA) -> dict:
    """{"abs_rel", "coverage", "pixels"}: mean |d̂ - d| / d over reference pixels with a rendered surface."""
    pred, gt = _flat(pred_depth, "pred_depth").detach(), _flat(gt_depth, "gt_depth").detach()
    if pred.shape != gt.shape:
        raise ValueError(f"pred_depth {list(pred.shape)} and gt_depth {list(gt.shape)} differ in shape")
    ref = reference_valid(gt, valid)
    use = ref & rendered_surface(pred, alpha, min_alpha)
    n_ref, n = int(ref.sum()), int(use.sum())
    if n == 0:
        return {"abs_rel": float("nan"), "coverage": 0.0 if n_ref else float("nan"), "pixels": 0}
    p, g = pred[use].double(), gt[use].double()
    return {"abs_rel": float(((p - g).abs() / g).mean()), "coverage": n / n_ref, "pixels": n}


def evaluate_depth(render_fn: Callable, views: Sequence, *, num_primitives: Optional[int] = None,
                   num_pairs: int = DEFAULT_PAIRS, margin: float = DEFAULT_MARGIN,
                   max_distance: Optional[float] = None, min_alpha: float = DEFAULT_MIN_ALPHA, seed: int = 0) -> dict:
    """Depth metrics over views that carry a reference `depth` ([H, W, 1]; +inf sky, 0 unknown).

    render_fn(view) -> an object with `.depth` and `.alpha` ([H, W, 1]), e.g.
    `lambda v: trainer.render(v, ("depth", "alpha"))`. Returns {"depth_order", "abs_rel", "coverage",
    "num_views", "num_pairs", "num_primitives", "per_view": {name: {...}}}; means are over views (pair-weighted
    for depth_order). Views without a reference depth are skipped; none at all raises."""
    per_view, total_pairs, correct = {}, 0, 0.0
    with torch.no_grad():
        for k, view in enumerate(views):
            gt = getattr(view, "depth", None)
            if gt is None:
                continue
            out = render_fn(view)
            depth, alpha = out.depth, out.alpha
            mask = getattr(view, "mask", None)
            order = depth_order_accuracy(depth, gt.to(depth.device), alpha=alpha, valid=mask, num_pairs=num_pairs,
                                         margin=margin, max_distance=max_distance, min_alpha=min_alpha,
                                         seed=seed + k)
            rel = abs_rel(depth, gt.to(depth.device), alpha=alpha, valid=mask, min_alpha=min_alpha)
            per_view[getattr(view, "name", str(k))] = {"depth_order": order["accuracy"], "pairs": order["pairs"],
                                                       "abs_rel": rel["abs_rel"], "coverage": rel["coverage"]}
            if order["pairs"]:
                total_pairs += order["pairs"]
                correct += order["accuracy"] * order["pairs"]
    if not per_view:
        raise ValueError("views: none has a reference depth map to score against")
    rels = [v["abs_rel"] for v in per_view.values() if not math.isnan(v["abs_rel"])]
    covs = [v["coverage"] for v in per_view.values() if not math.isnan(v["coverage"])]
    return {"depth_order": correct / total_pairs if total_pairs else float("nan"),
            "abs_rel": sum(rels) / len(rels) if rels else float("nan"),
            "coverage": sum(covs) / len(covs) if covs else float("nan"),
            "num_views": len(per_view), "num_pairs": total_pairs, "num_primitives": num_primitives,
            "per_view": per_view}
