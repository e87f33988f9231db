"""Dropout of primitives in training renders (`train.drop_rate`; DropGaussian, Park et al., CVPR 2025): each
training view renders with every primitive kept with probability 1 - r, the kept ones' opacities divided by 1 - r
so that a pixel's expected coverage is unchanged. With few views a model fits them with many small primitives that
only work together; renders that miss a random share of them make each primitive fit the images on its own.
Evaluation and every output render the whole model."""
from __future__ import annotations

from typing import Optional

import torch

from warpgs.train.few_views import FewViewsRule

# train.drop_rate=auto: AUTO_RATE_3 with at most 3 training views, AUTO_RATE with 4 and with more than
# AUTO_OFF_MAX_VIEWS, off in between. Measured on real captures (H200, 3 seeds, paired; docs/sparse_view.md): on 7
# LLFF scenes at 3 views none is 0.10 dB under 0.3 and 0.1 ties with 0.3 (+0.04 +- 0.08; the preset's figures are
# measured at 0.3); at 4 views 0.3 is 0.12 +- 0.03 under 0.1. Around 360° captures 0.1 against none: +0.16 / +0.38 /
# -0.09 / +0.25 at 24 views of four, +0.42 / +0.17 / +0.15 / +0.10 at 12 views (0.2 costs more than it gives). 9
# views of a real light field lose 0.56 +- 0.08 dB at 0.1 and 5-8 views are unmeasured, so auto leaves it off there.
# Forward-facing captures with more than 9 views are unmeasured.
AUTO_RATE_3 = 0.3
AUTO_RATE = 0.1
AUTO_MAX_VIEWS = 4
AUTO_OFF_MAX_VIEWS = 9
RULE = FewViewsRule("primitive dropout", "train.drop_rate", AUTO_OFF_MAX_VIEWS, 0.0,
                    fewer=((3, AUTO_RATE_3), (AUTO_MAX_VIEWS, AUTO_RATE)), more=AUTO_RATE)


def drop_rate_for(setting, num_train_views: int) -> float:
    """The dropout rate that train.drop_rate asks for with this many training views."""
    return RULE.value(setting, num_train_views, float)


def rate_at(rate: float, schedule: str, step: int, steps: int) -> float:
    """The dropout rate of training step `step` (0-based) of `steps`: `rate` throughout ("constant"), or rising
    linearly from rate / steps at the first step to `rate` at the last ("ramp", DropGaussian's r_t = r * t / T: the
    early steps, which place the primitives, see nearly all of them)."""
    if schedule == "ramp":
        return rate * min(step + 1, steps) / max(steps, 1)
    return rate


def dropout_note(setting, rate: float, num_train_views: int) -> str:
    """The start line's words on dropout: its rate when on, why not when "auto" left it off, else ""."""
    return RULE.note(setting, rate, num_train_views, f"; primitive dropout {rate:g}")


def manner_note(schedule: str, near_power: float, rate: float) -> str:
    """The start line's words on how dropout draws: a rate ramped up, near primitives more often ("" for neither);
    with dropout off, that a train.drop_near asked for does nothing."""
    if not rate:
        return "; train.drop_near unused (no dropout)" if near_power else ""
    return ((" ramped up from 0" if schedule == "ramp" else "") +
            (f", near primitives more often (power {near_power:g})" if near_power else ""))


def dropped_opacities(opacities: torch.Tensor, rate: float,
                      probabilities: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Opacities [N] or [N, 1] with a random share `rate` of the rows zeroed and the rest divided by 1 - rate
    (differentiable; the kept rows' gradients scaled alike). probabilities: [N] per-row drop probabilities instead
    (each kept row divided by its own 1 - p). rate 0: `opacities` itself."""
    if rate <= 0.0:
        return opacities
    p = (torch.full((opacities.shape[0],), float(rate), device=opacities.device, dtype=opacities.dtype)
         if probabilities is None else probabilities.to(opacities.device, opacities.dtype))
    keep = torch.rand(opacities.shape[0], device=opacities.device) >= p
    scale = keep.to(opacities.dtype) / (1.0 - p)
    return opacities * scale.view((-1,) + (1,) * (opacities.dim() - 1))


# train.drop_near: no primitive's drop probability goes above this, so even the nearest are drawn now and then;
# depths under NEAREST_DEPTH_SHARE of the median count as that, so one primitive at the camera cannot take the
# whole rate (nor its weight overflow).
MAX_NEAR_PROBABILITY = 0.9
NEAREST_DEPTH_SHARE = 0.1


def near_probabilities(means: torch.Tensor, viewmat: torch.Tensor, rate: float, power: float) -> torch.Tensor:
    """[N] drop probabilities for one view (train.drop_near): in front of the camera proportional to (median depth /
    depth) ** power, capped at MAX_NEAR_PROBABILITY and averaging `rate` (what the cap cuts goes to the rest);
    behind it `rate` (not drawn anyway). Primitives near a training camera are where few views leave floaters that
    each view sees against the scene behind them (sparse_view.md's figurine haze; D2GS, Song et al. 2025, drops by
    depth and density; this is our own form of the depth half)."""
    means = means.detach()
    viewmat = torch.as_tensor(viewmat, device=means.device, dtype=means.dtype)
    depth = means @ viewmat[2, :3] + viewmat[2, 3]
    p = torch.full_like(depth, float(rate))
    front = depth > 0
    if not bool(front.any()):
        return p
    z = depth[front]
    median = z.median()
    weight = (median / z.clamp(min=NEAREST_DEPTH_SHARE * median)).pow(power)
    p[front] = _capped_shares(weight, rate)
    return p


def _capped_shares(weight: torch.Tensor, rate: float, rounds: int = 4) -> torch.Tensor:
    """Probabilities proportional to `weight`, none above MAX_NEAR_PROBABILITY, averaging `rate`: what the capped
    rows cannot take goes to the others in proportion (a few rounds of water-filling, no host reads)."""
    total = rate * weight.numel()
    p = (total / weight.sum()) * weight
    for _ in range(rounds):
        capped = p >= MAX_NEAR_PROBABILITY
        left = total - MAX_NEAR_PROBABILITY * capped.sum()
        free = torch.where(capped, torch.zeros_like(weight), weight).sum().clamp_min(1e-12)
        p = torch.where(capped, torch.full_like(p, MAX_NEAR_PROBABILITY), (left / free) * weight)
    return p.clamp(max=MAX_NEAR_PROBABILITY)
