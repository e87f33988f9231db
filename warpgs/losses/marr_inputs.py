"""What the Marr depth terms (marr.py) read, checked: their settings (`SETTINGS`, `configure`), the render's inverse
depth and alpha, and the batch's prior, masks and confidence (the module doc of marr.py says what each is and why).
Checks run eagerly; `_maps` and what it calls are tensor work only, so a GPU training step can replay them from a
CUDA graph (marr.py)."""
from __future__ import annotations

import weakref
from dataclasses import dataclass, fields
from typing import Optional

import torch

from warpgs.losses.registry import batch_field, render_output

PRIOR_KEY = "inv_depth_prior"
VALID_KEY = "inv_depth_valid"
CONFIDENCE_KEY = "inv_depth_confidence"
MASK_KEY = "mask"


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
    the depth terms (marr.py, which graph the same two steps) and losses/depth_patch.py take them."""
    settings = current_settings()
    inv, alpha, prior, masks, conf = checked_maps(render_out, batch, settings)
    return _maps(settings, inv, alpha, prior, masks, conf)
