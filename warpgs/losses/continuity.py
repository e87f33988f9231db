"""Good continuation (`depth_smooth`): where the 2.5D sketch is silent, rendered depth should continue smoothly.

Beyond the Marr–Gestalt paper and off unless a config lists it (`losses.depth_smooth=W`): on seven real LLFF scenes
(3 views, H200, 3 seeds) weight 1 tied with none (-0.01 +- 0.05 dB) and 10 cost 0.52 (docs/sparse_view.md).
The plane-sweep prior is confident on texture and silent on walls, floors and sky, exactly where three views leave
the model free to put floaters. This term asks the rendered inverse depth
to have no curvature there (Gestalt good continuation):

    L = Σ w (|∂xx d| + 2 |∂xy d| + |∂yy d|) / Σ w,   d = D̂ / mean(D̂)

- second order, so planes at any slant (a floor, a wall seen obliquely) cost nothing;
- d is the rendered inverse depth (marr.py's alpha-normalised form) over its mean on the covered pixels, so the
  term is blind to the scene's units;
- w = exp(-EDGE |∇I|) x (1 - c): low across image edges (where depth may break) and where the prior is confident
  (c, its per-pixel confidence; 1 where it has no valid value or the view has no prior at all), so it fills in what
  the depth terms leave free instead of fighting them;
- only pixels whose whole 3x3 window is covered (alpha >= marr's alpha_min) count.
"""
from __future__ import annotations

from typing import Optional

import torch
from kornia.filters import spatial_gradient

from warpgs.losses.marr import (DEPTH_SCHEDULE, OUTPUTS, PRIOR_KEY, SETTINGS, _bchw, masked_mean,
                                prior_and_mask, prior_weight, rendered_inverse_depth, window_min, window_valid)
from warpgs.losses.photometric import IMAGE_KEY
from warpgs.losses.registry import batch_field, register_loss
from warpgs.losses.sobel import sobel_gradient

EDGE = 10.0  # edge sensitivity: an image step of 0.1 per pixel (normalised Sobel) leaves e^-1 of the weight


def edge_weight(image: torch.Tensor, edge: float = EDGE) -> torch.Tensor:
    """[B, 3, H, W] image in [0, 1] -> [B, 1, H, W] exp(-edge x mean over channels of |∂x I| + |∂y I|)."""
    g = sobel_gradient(image)  # [B, C, 2, H, W]
    return torch.exp(-edge * g.abs().sum(2).mean(1, keepdim=True))


def curvature_l1(pred: torch.Tensor, mask: torch.Tensor, weight: Optional[torch.Tensor] = None,
                 scale: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Weighted mean over pixels with an all-covered 3x3 window of |∂xx d| + 2|∂xy d| + |∂yy d|, d = pred / scale;
    maps [B, 1, H, W]. scale: by default pred's mean on mask, detached (a unit, not something to optimise)."""
    if scale is None:
        with torch.no_grad():
            scale = masked_mean(pred, mask).clamp_min(1e-12)
    d = torch.where(mask, pred / scale, torch.zeros_like(pred))
    h = spatial_gradient(d, mode="diff", order=2, normalized=True).abs()  # [B, 1, 3, H, W]: xx, xy, yy
    curvature = h[:, :, 0] + 2.0 * h[:, :, 1] + h[:, :, 2]
    return masked_mean(curvature, window_valid(mask), weight)


def silence(batch, like: torch.Tensor) -> torch.Tensor:
    """[B, 1, H, W]: how little the prior says at each pixel, 1 - confidence where it is valid, 1 elsewhere (and
    everywhere when the view has no prior)."""
    try:
        batch_field(batch, PRIOR_KEY)
    except ValueError:
        return torch.ones_like(like)
    _, valid = prior_and_mask(batch, like)
    conf = prior_weight(batch, like, power=1.0)
    known = valid.to(like.dtype) * (torch.ones_like(like) if conf is None else conf)
    return 1.0 - known


@register_loss("depth_smooth", outputs=OUTPUTS, weight=1.0, schedule=DEPTH_SCHEDULE)
def depth_smooth(render_out, batch, model, step) -> torch.Tensor:
    """L_smooth: edge-aware curvature of the rendered inverse depth where the prior is silent (module doc)."""
    pred, alpha = rendered_inverse_depth(render_out)
    image = _bchw(batch_field(batch, IMAGE_KEY), f"batch.{IMAGE_KEY}", channels=3).to(pred)
    if image.shape[-2:] != pred.shape[-2:]:
        raise ValueError(f"batch.{IMAGE_KEY}: {list(image.shape[-2:])} does not match the render "
                         f"{list(pred.shape[-2:])}")
    covered = alpha.detach() >= SETTINGS.alpha_min
    weight = window_min(edge_weight(image) * silence(batch, pred))
    return curvature_l1(pred, covered, weight)

