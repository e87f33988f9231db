"""Patch-normalised depth (`depth_patch`): DNGaussian's local depth normalisation as a registered term, beyond the
Marr–Gestalt paper and off unless a config lists it (`losses.depth_patch`; benchmarks/sparse.py's `depth_patch`
setting puts it on the preset).

Within every PATCH x PATCH block, the rendered inverse depth D̂ and the prior D* are each normalised by their own
mean and standard deviation over the block's valid pixels, and the term is the mean |norm(D̂) - norm(D*)| over
those pixels (confidence-weighted as the Marr terms, marr.py). The comparison is blind to any positive affine map
of depth within a block, so it asks only for the prior's local shape: what a monocular or plane-sweep prior gets
right even where its scale drifts across the image, which the global L1 (`depth`) and the 3x3 statistics
(`depth_local`) also penalise. Blocks with under half their pixels valid, or whose prior is flat (its standard
deviation under FLAT of the prior's mean magnitude, where normalising would amplify noise), are left out. The block
grid moves with the step (a fixed grid would leave its seams unconstrained).
"""
from __future__ import annotations

import math
from typing import Optional, Tuple

import torch
import torch.nn.functional as F

from warpgs.losses.marr import DEPTH_SCHEDULE, OUTPUTS, PRIOR_KEY, depth_inputs, masked_mean
from warpgs.losses.registry import register_loss

PATCH = 8  # block side in pixels
MIN_VALID = 0.5  # fraction of a block's pixels that must be valid
FLAT = 1e-3  # a block's prior std below this fraction of the prior's mean |D*| counts as flat


def grid_offset(step: int, patch: int = PATCH) -> Tuple[int, int]:
    """Where the block grid starts at `step` (rows, columns): a walk over the patch x patch offsets."""
    return (3 * step) % patch, (5 * step) % patch


def patch_normalised_l1(pred: torch.Tensor, prior: torch.Tensor, mask: torch.Tensor,
                        weight: Optional[torch.Tensor] = None, patch: int = PATCH,
                        offset: Tuple[int, int] = (0, 0)) -> torch.Tensor:
    """Mean over the pixels of usable blocks of |norm(pred) - norm(prior)| (each normalised by its own block mean and
    std); pred, prior, mask (bool) and weight as [B, 1, H, W]. 0 (still connected to pred) without usable blocks."""
    H, W = pred.shape[-2:]
    top, left = (patch - offset[0]) % patch, (patch - offset[1]) % patch
    bottom = math.ceil((H + top) / patch) * patch - H - top
    right = math.ceil((W + left) / patch) * patch - W - left
    pad = (left, right, top, bottom)
    m = F.pad(mask.to(pred.dtype), pad)
    with torch.no_grad():  # both maps shifted by one constant: the block statistics lose less to cancellation
        centre = masked_mean(prior, mask)
        scale = masked_mean(prior.abs(), mask)
    a = F.pad(torch.where(mask, pred - centre, torch.zeros_like(pred)), pad)
    b = F.pad(torch.where(mask, prior - centre, torch.zeros_like(prior)), pad)
    area = float(patch * patch)
    count = F.avg_pool2d(m, patch) * area
    n = count.clamp_min(1.0)

    def normalised(x):
        mean = F.avg_pool2d(x, patch) * area / n
        var = (F.avg_pool2d(x * x, patch) * area / n - mean * mean).clamp_min(0.0)
        # the floor keeps the gradient finite on flat renders (and the tiny term, blocks with no valid pixel)
        std = torch.sqrt(var + (FLAT * scale) ** 2 + 1e-20)
        return (x - _up(mean, patch)) / _up(std, patch), var

    na, _ = normalised(a)
    nb, var_b = normalised(b)
    with torch.no_grad():
        usable = (count >= MIN_VALID * area) & (var_b >= (FLAT * scale) ** 2)
        keep = (m > 0) & _up(usable, patch)
    w = None if weight is None else F.pad(weight, pad)
    return masked_mean((na - nb).abs(), keep, w)


def _up(t: torch.Tensor, patch: int) -> torch.Tensor:
    """A per-block map back at pixel resolution."""
    return t.repeat_interleave(patch, dim=-2).repeat_interleave(patch, dim=-1)


@register_loss("depth_patch", outputs=OUTPUTS, weight=1.0, schedule=DEPTH_SCHEDULE, batch=(PRIOR_KEY,))
def depth_patch(render_out, batch, model, step) -> torch.Tensor:
    """L_patch = mean |norm_P(D̂) - norm_P(D*)| over PATCH x PATCH blocks (DNGaussian's local depth normalisation)."""
    pred, prior, mask, weight = depth_inputs(render_out, batch)
    return patch_normalised_l1(pred, prior, mask, weight, offset=grid_offset(int(step)))
