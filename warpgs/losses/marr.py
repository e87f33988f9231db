"""The 2.5D-sketch ("Marr") depth terms of the sparse-view method, on inverse depth.

Registered losses (each `(render_out, batch, model, step) -> scalar`, removable by weight 0):

    depth        mean |D̂ - D*|                                     over valid prior pixels
    depth_grad   mean |∇D̂ - ∇D*|_1   (kornia Sobel, per pixel)     over pixels whose 3x3 window is all valid
    depth_local  mean |μ_D̂ - μ_D*| + |σ²_D̂ - σ²_D*|   (3x3 box)    over pixels whose 3x3 window is all valid

Default weight 1 with the exponential schedule 1 -> 0.01 over training (`("exp", 1.0, 0.01)`), as the paper.

The rendered inverse depth D̂. The prior D* is inverse depth aligned (scale + shift) to the SfM points, i.e. to
1/z of *surface* points; it has no notion of coverage. Of the two renders available,
  - `inv_depth` = Σ w_i / z_i is the inverse depth composited over a background at infinity: it is alpha x
    (mean inverse depth) and under-reads wherever the splats do not yet cover the pixel;
  - `inv_depth / alpha` = Σ w_i / z_i / Σ w_i is the weight-averaged inverse depth of what the pixel shows,
    which is exactly what an aligned prior measures (1/z of the surface point seen through the pixel).
We use the second (normalised) form, and leave out pixels whose alpha is below `alpha_min` (default 0.1),
where the normalisation would be dominated by one faint splat: coverage is the photometric terms' business.
(1/depth, the reciprocal of the expected z, would be a harmonic-type mean and biased to the far side at depth
edges; the normalised accumulated inverse depth averages in the same space as the prior.) Gradients flow
through both `inv_depth` and `alpha`.

Batch fields (as the trainer fills them from the scene's View): `inv_depth_prior` [H, W, 1] (or [B, H, W, 1])
and `inv_depth_valid` (same shape, bool). An optional `mask` (pixels to use) is and-ed in. Pixels with a
non-finite or non-positive prior are invalid whatever the mask says.

Confidence (issue 15). When the prior comes with a per-pixel confidence c in [0, 1] (`inv_depth_confidence`, in
the batch or on `batch["view"]`; the built-in plane sweep writes one), every term is a weighted mean with weight
c ** `confidence_power` over its pixels (for the 3x3 terms, the smallest c in the window, as validity is
eroded): a weighted mean keeps each term's scale, so λ1..λ3 keep their meaning, while pixels the stereo is
unsure of (weakly textured, confirmed by fewer views) pull less. confidence_power 0 ignores the confidence.

Options that the config's loss entries cannot carry (they take only weight and schedule) live in
`SETTINGS` (change them with `configure(alpha_min=...)`, e.g. from a module listed under `imports`).

On a GPU training step each term's tensor work (normalisation, mask, weight, term) replays from a CUDA graph after
its checks, one launch a direction (cuda_graphs.py; WARPGS_LOSS_GRAPHS=0 turns it off); a graph per settings. Each
graph keeps buffers the size of its images (552 MiB for 9 graphs at 960x540 on an H200,
benchmarks/marr_graphs.py): a term holds at most 2 settings x 4 image sizes of them, a training run one.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from kornia.filters import box_blur

from warpgs.losses.cuda_graphs import KeyedGraphs
from warpgs.losses.marr_inputs import (  # noqa: F401  (the terms' settings and inputs, kept importable from here)
    CONFIDENCE_KEY, MASK_KEY, PRIOR_KEY, SETTINGS, VALID_KEY, MarrSettings, _bchw, _maps, checked_maps,
    checked_settings, configure, current_settings, depth_inputs, prior_and_mask, prior_weight, rendered_inverse_depth)
from warpgs.losses.registry import register_loss
from warpgs.losses.sobel import sobel_gradient

OUTPUTS = ("alpha", "inv_depth")
DEPTH_SCHEDULE = ("exp", 1.0, 0.01)  # λ1..λ3: 1 at step 0, 0.01 at the last step, log-linear in between


# ----- pure functions on [B, 1, H, W] maps (tests use these directly) ------------------------------------------
def window_valid(mask: torch.Tensor) -> torch.Tensor:
    """[B, 1, H, W] bool -> bool: the pixel's whole 3x3 window lies inside the image and is valid (an erosion
    with out-of-image pixels counted invalid)."""
    inv = F.pad((~mask).float(), (1, 1, 1, 1), value=1.0)
    return F.max_pool2d(inv, 3, stride=1) < 0.5


def masked_mean(value: torch.Tensor, mask: torch.Tensor, weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(Weighted) mean of `value` over `mask` (broadcast over channels); 0 (still connected to the graph) when
    empty. weight: [B, 1, H, W] >= 0, or None for a plain mean."""
    m = mask.to(value.dtype)
    if weight is not None:
        m = m * weight.to(value.dtype)
    count = m.sum() * (value.numel() / m.numel())
    # A plain mean divides by the pixel count (>= 1 when any); a weighted one by the weight sum, which may be tiny.
    return (value * m).sum() / (count.clamp_min(1.0) if weight is None else count.clamp_min(1e-6))


def window_min(weight: torch.Tensor) -> torch.Tensor:
    """[B, 1, H, W] -> the smallest value in each pixel's 3x3 window (out-of-image counts as 0)."""
    return -F.max_pool2d(F.pad(-weight, (1, 1, 1, 1), value=0.0), 3, stride=1)


def depth_l1(pred: torch.Tensor, prior: torch.Tensor, mask: torch.Tensor,
             weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """mean |pred - prior| over mask, weighted by `weight` when given; maps [B, 1, H, W]."""
    diff = torch.where(mask, pred - prior, torch.zeros_like(pred))
    return masked_mean(diff.abs(), mask, weight)


def depth_gradient_l1(pred: torch.Tensor, prior: torch.Tensor, mask: torch.Tensor,
                      weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """mean over pixels with an all-valid 3x3 window of |∂x D̂ - ∂x D*| + |∂y D̂ - ∂y D*|, with kornia's
    normalised Sobel (a ramp of slope 1 per pixel has gradient 1); weighted by the window's smallest weight."""
    diff = torch.where(mask, pred - prior, torch.zeros_like(pred))  # ∇ is linear: ∇D̂ - ∇D* = ∇(D̂ - D*)
    g = sobel_gradient(diff)  # [B, 1, 2, H, W]; kornia's, without its per-call host copy (sobel.py)
    inner = window_valid(mask)
    return masked_mean(g.abs().sum(2), inner, None if weight is None else window_min(weight))


def local_stats(x: torch.Tensor) -> tuple:
    """(mean, variance) over each pixel's 3x3 window via kornia box filters: E[x], E[x²] - E[x]²."""
    mean = box_blur(x, (3, 3))
    var = (box_blur(x * x, (3, 3)) - mean * mean).clamp_min(0.0)
    return mean, var


def depth_local_l1(pred: torch.Tensor, prior: torch.Tensor, mask: torch.Tensor,
                   weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """mean over pixels with an all-valid 3x3 window of |μ_D̂ - μ_D*| + |σ²_D̂ - σ²_D*| (population variance);
    weighted by the window's smallest weight."""
    inner = window_valid(mask)
    # Both maps are shifted by the same constant (the prior's mean): the statistics' differences do not change,
    # and E[x²] - E[x]² loses less to float32 cancellation.
    with torch.no_grad():
        centre = masked_mean(prior, mask)  # 0 without valid pixels (no host read to ask whether there are any)
    zero = torch.zeros_like(pred)
    mu_p, var_p = local_stats(torch.where(mask, pred - centre, zero))
    mu_t, var_t = local_stats(torch.where(mask, prior - centre, zero))
    return masked_mean((mu_p - mu_t).abs() + (var_p - var_t).abs(), inner,
                       None if weight is None else window_min(weight))


# ----- the registered terms: checks eager, the rest one graph replay a direction on a GPU training step -------
TERMS = {"depth": depth_l1, "depth_grad": depth_gradient_l1, "depth_local": depth_local_l1}


def term_core(name: str, settings: tuple, has_confidence: bool):
    """Term `name` as fn(inv_depth, alpha, prior, *masks[, confidence]) on checked_maps' maps, with `settings`
    (current_settings()) fixed: the alpha normalisation, the mask, the confidence weight and the term."""
    term = TERMS[name]

    def core(inv, alpha, prior, *rest):
        masks, conf = (rest[:-1], rest[-1]) if has_confidence else (rest, None)
        return term(*_maps(settings, inv, alpha, prior, masks, conf))

    core.__name__ = core.__qualname__ = f"{name}_core"
    return core


# A graph per term, settings, confidence or not (the key) and argument shapes; CPU, evaluation: term_core as is.
_GRAPHS = {name: KeyedGraphs(lambda key, name=name: term_core(name, *key)) for name in TERMS}


def _graphed_term(name: str, render_out, batch) -> torch.Tensor:
    settings = current_settings()
    inv, alpha, prior, masks, conf = checked_maps(render_out, batch, settings)
    args = (inv, alpha, prior, *masks) + (() if conf is None else (conf,))
    # A copy: a replay's output is the graph's buffer, which the next replay overwrites, and compute_losses keeps
    # the value (read a step later).
    return _GRAPHS[name]((settings, conf is not None), *args).clone()


@register_loss("depth", outputs=OUTPUTS, weight=1.0, schedule=DEPTH_SCHEDULE, batch=(PRIOR_KEY,))
def depth(render_out, batch, model, step) -> torch.Tensor:
    """L_D = mean |D̂ - D*| over valid prior pixels (paper eq. 4)."""
    return _graphed_term("depth", render_out, batch)


@register_loss("depth_grad", outputs=OUTPUTS, weight=1.0, schedule=DEPTH_SCHEDULE, batch=(PRIOR_KEY,))
def depth_grad(render_out, batch, model, step) -> torch.Tensor:
    """L_grad = mean |∇D̂ - ∇D*| (paper eq. 5)."""
    return _graphed_term("depth_grad", render_out, batch)


@register_loss("depth_local", outputs=OUTPUTS, weight=1.0, schedule=DEPTH_SCHEDULE, batch=(PRIOR_KEY,))
def depth_local(render_out, batch, model, step) -> torch.Tensor:
    """L_local = mean |μ_D̂ - μ_D*| + |σ²_D̂ - σ²_D*| over 3x3 windows (paper eqs. 6-8)."""
    return _graphed_term("depth_local", render_out, batch)
