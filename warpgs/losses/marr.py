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

import weakref
from dataclasses import dataclass, fields
from typing import Optional

import torch
import torch.nn.functional as F
from kornia.filters import box_blur

from warpgs.losses.cuda_graphs import KeyedGraphs
from warpgs.losses.registry import batch_field, register_loss, render_output
from warpgs.losses.sobel import sobel_gradient

PRIOR_KEY = "inv_depth_prior"
VALID_KEY = "inv_depth_valid"
CONFIDENCE_KEY = "inv_depth_confidence"
MASK_KEY = "mask"
OUTPUTS = ("alpha", "inv_depth")
DEPTH_SCHEDULE = ("exp", 1.0, 0.01)  # λ1..λ3: 1 at step 0, 0.01 at the last step, log-linear in between


@dataclass
class MarrSettings:
    alpha_min: float = 0.1  # pixels whose rendered alpha is below this are left out (0: keep all covered pixels)
    alpha_eps: float = 1e-6  # guard of the alpha normalisation
    confidence_power: float = 1.0  # per-pixel weight = confidence ** this (0: ignore the prior's confidence)


SETTINGS = MarrSettings()


def checked_settings(**kwargs) -> dict:
    """{key: float} for settings of MarrSettings, each a finite number >= 0; anything else is a ValueError naming
    it (configure's check, also run by callers that pass settings on, e.g. benchmarks/sparse.py --marr)."""
    names = {f.name for f in fields(MarrSettings)}
    checked = {}
    for key, value in kwargs.items():
        if key not in names:
            raise ValueError(f"marr.configure: unknown setting {key!r}; choose from {sorted(names)}")
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"marr.configure: {key}={value!r} is not a number") from None
        if not (number >= 0.0 and number < float("inf")):
            raise ValueError(f"marr.configure: {key} must be finite and >= 0, got {number}")
        checked[key] = number
    return checked


def configure(**kwargs) -> MarrSettings:
    """Change the module's settings (see MarrSettings); returns them."""
    for key, value in checked_settings(**kwargs).items():
        setattr(SETTINGS, key, value)
    return SETTINGS


# ----- pure functions on [B, 1, H, W] maps (tests use these directly) ------------------------------------------
def _bchw(x: torch.Tensor, name: str, channels: int = 1) -> torch.Tensor:
    """[H, W] (one channel), [H, W, C] or [B, H, W, C] -> [B, C, H, W], C = channels."""
    if x.dim() == 2 and channels == 1:
        x = x[..., None]
    if x.dim() == 3:
        x = x[None]
    if x.dim() != 4 or x.shape[-1] != channels:
        shapes = ("[H, W], [H, W, 1] or [B, H, W, 1]" if channels == 1
                  else f"[H, W, {channels}] or [B, H, W, {channels}]")
        raise ValueError(f"{name}: expected {shapes}, got {list(x.shape)}")
    return x.permute(0, 3, 1, 2)


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


# ----- from the render and the batch ---------------------------------------------------------------------------
# In two parts, so that a GPU training step replays each term's tensor work from a CUDA graph (cuda_graphs.py):
# the checks (shapes, a missing prior, the confidence's finiteness: a host read) run eagerly on the maps as given,
# and `_maps` and the terms are tensor work only, on the checked maps, with the settings fixed.
def _render_maps(render_out) -> tuple:
    """(accumulated inverse depth, alpha) as [B, 1, H, W] (views of the render's maps)."""
    inv = _bchw(render_output(render_out, "inv_depth"), "render_out.inv_depth")
    alpha = _bchw(render_output(render_out, "alpha"), "render_out.alpha")
    return inv, alpha


def _normalised(inv: torch.Tensor, alpha: torch.Tensor, alpha_eps: float) -> torch.Tensor:
    return inv / alpha.clamp_min(max(alpha_eps, 1e-12))


def rendered_inverse_depth(render_out, alpha_eps: Optional[float] = None) -> tuple:
    """(D̂, alpha) as [B, 1, H, W]: the alpha-normalised accumulated inverse depth (see module doc)."""
    inv, alpha = _render_maps(render_out)
    return _normalised(inv, alpha, SETTINGS.alpha_eps if alpha_eps is None else alpha_eps), alpha


def _batch_prior(batch, dtype: torch.dtype, device: torch.device, size) -> torch.Tensor:
    """batch["inv_depth_prior"] as [B, 1, H, W] in `dtype` on `device`, its H, W checked against `size`."""
    try:
        prior = batch_field(batch, PRIOR_KEY)
    except ValueError:
        raise ValueError(f"batch: the depth terms need {PRIOR_KEY!r} (an aligned inverse-depth prior): the scene has "
                         "none for this view; set data.depth_priors (a folder of priors, or 'estimate' for the "
                         "built-in plane-sweep stereo), or give depth/depth_grad/depth_local weight 0"
                         ) from None
    prior = _bchw(prior, f"batch.{PRIOR_KEY}").to(device=device, dtype=dtype)
    if prior.shape[-2:] != tuple(size):
        raise ValueError(f"batch.{PRIOR_KEY}: {list(prior.shape[-2:])} does not match the render {list(size)}")
    return prior


def _batch_masks(batch, device: torch.device) -> tuple:
    """The batch's pixel masks that are present (inv_depth_valid, mask) as bool [B, 1, H, W] on `device`."""
    masks = []
    for key in (VALID_KEY, MASK_KEY):
        try:
            m = batch_field(batch, key)
        except ValueError:
            continue
        masks.append(_bchw(m, f"batch.{key}").to(device=device, dtype=torch.bool))
    return tuple(masks)


def _masked_prior(prior: torch.Tensor, masks, like: torch.Tensor, alpha: Optional[torch.Tensor],
                  alpha_min: float) -> tuple:
    """(D*, mask): the valid prior pixels (finite, > 0, in every mask, alpha >= alpha_min), D* 0 elsewhere."""
    prior = prior.expand_as(like)
    mask = torch.isfinite(prior) & (prior > 0)
    for m in masks:
        mask = mask & m
    if alpha is not None and alpha_min > 0:
        mask = mask & (alpha.detach() >= alpha_min)
    prior = torch.where(mask, prior, torch.zeros_like(prior))
    return prior, mask


def prior_and_mask(batch, like: torch.Tensor, alpha: Optional[torch.Tensor] = None,
                   alpha_min: Optional[float] = None) -> tuple:
    """(D*, mask) as [B, 1, H, W] matching `like`: valid prior, and-ed with batch["mask"] and alpha >= alpha_min."""
    amin = SETTINGS.alpha_min if alpha_min is None else alpha_min
    prior = _batch_prior(batch, like.dtype, like.device, like.shape[-2:])
    return _masked_prior(prior, _batch_masks(batch, like.device), like, alpha, amin)


# Confidence maps already found finite, by identity and version (weakly held, so no map outlives its view): a view
# keeps its map for the whole run, and the check is a host read (a stall on a GPU) on every step otherwise.
_SEEN_FINITE: dict = {}
_SEEN_FINITE_SIZE = 1024


def _seen_finite(t: torch.Tensor) -> bool:
    if t.is_inference():  # no version counter to key on: checked every time
        return False
    seen = _SEEN_FINITE.get(id(t))
    if seen is not None and seen[0]() is t and seen[1] == t._version:
        return True
    if len(_SEEN_FINITE) >= _SEEN_FINITE_SIZE:
        _SEEN_FINITE.clear()
    return False


def _batch_confidence(batch, dtype: torch.dtype, device: torch.device, size) -> Optional[torch.Tensor]:
    """The prior's confidence as [B, 1, H, W] in `dtype` on `device` (batch["inv_depth_confidence"] or the batch's
    view's), checked: H, W against `size`, finite (once per map: `_seen_finite`); None when there is none."""
    try:
        conf = batch_field(batch, CONFIDENCE_KEY)
    except ValueError:
        view = batch.get("view") if isinstance(batch, dict) else getattr(batch, "view", None)
        conf = getattr(view, CONFIDENCE_KEY, None)
        if conf is None:
            return None
    given = conf
    conf = _bchw(conf, f"batch.{CONFIDENCE_KEY}").to(device=device, dtype=dtype)
    if conf.shape[-2:] != tuple(size):
        raise ValueError(f"batch.{CONFIDENCE_KEY}: {list(conf.shape[-2:])} does not match the render {list(size)}")
    if not _seen_finite(given) and not bool(torch.isfinite(conf).all()):
        raise ValueError(f"batch.{CONFIDENCE_KEY}: contains NaN or Inf")
    if not given.is_inference():
        _SEEN_FINITE[id(given)] = (weakref.ref(given), given._version)
    return conf


def _confidence_weight(conf: torch.Tensor, power: float, like: torch.Tensor) -> torch.Tensor:
    return conf.clamp(0.0, 1.0).pow(power).expand_as(like)


def prior_weight(batch, like: torch.Tensor, power: Optional[float] = None) -> Optional[torch.Tensor]:
    """confidence ** power as [B, 1, H, W] matching `like`, from batch["inv_depth_confidence"] or the batch's
    view; None when there is none or power is 0 (plain means)."""
    power = SETTINGS.confidence_power if power is None else power
    if power == 0:
        return None
    conf = _batch_confidence(batch, like.dtype, like.device, like.shape[-2:])
    return None if conf is None else _confidence_weight(conf, power, like)


def current_settings() -> tuple:
    """(alpha_eps, alpha_min, confidence_power) as the terms read them now: part of each graph's key."""
    return (float(SETTINGS.alpha_eps), float(SETTINGS.alpha_min), float(SETTINGS.confidence_power))


def checked_maps(render_out, batch, settings: tuple) -> tuple:
    """(inv_depth, alpha, prior, masks, confidence) as [B, 1, H, W], after every check the terms make (eager:
    shapes, a missing prior, the confidence's finiteness); confidence None when there is none or its power is 0."""
    inv, alpha = _render_maps(render_out)
    dtype, device = torch.promote_types(inv.dtype, alpha.dtype), inv.device
    size = torch.broadcast_shapes(inv.shape, alpha.shape)[-2:]  # D̂'s, as the division will make it
    prior = _batch_prior(batch, dtype, device, size)
    masks = _batch_masks(batch, device)
    conf = None if settings[2] == 0 else _batch_confidence(batch, dtype, device, size)
    return inv, alpha, prior, masks, conf


def _maps(settings: tuple, inv, alpha, prior, masks, conf) -> tuple:
    """(D̂, D*, mask, weight) from checked maps: tensor work only (graph-safe: no host reads, shapes fixed)."""
    alpha_eps, alpha_min, power = settings
    pred = _normalised(inv, alpha, alpha_eps)
    prior, mask = _masked_prior(prior, masks, pred, alpha, alpha_min)
    return pred, prior, mask, None if conf is None else _confidence_weight(conf, power, pred)


def depth_inputs(render_out, batch):
    """(rendered inverse depth, prior, valid mask, per-pixel weight) of a render against its batch's depth prior, as
    every depth term here (and losses/depth_patch.py) takes them."""
    settings = current_settings()
    inv, alpha, prior, masks, conf = checked_maps(render_out, batch, settings)
    return _maps(settings, inv, alpha, prior, masks, conf)


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
