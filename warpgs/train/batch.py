"""Bookkeeping of one step over a batch of views: what each view's render and backward leave behind (ViewPass),
and the batch's loss, per-term values and train PSNR from the per-view sums (summed over ranks when distributed).

The render op takes one camera, so a batch is rendered one view at a time: render, loss / B, backward, then the
next view. Gradients accumulate in .grad as the mean over the batch, and only one view's render buffers are alive
at a time (the fast GPU path also reuses its workspace between calls, so a view's backward must come before the
next view's render)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import torch

from warpgs.losses.registry import LossResult


@dataclass
class ViewPass:
    """One view of the step, after its backward."""
    view: object
    result: LossResult  # this view's losses (total not divided by the batch size)
    visible: Optional[torch.Tensor] = None  # [N] bool, when densifying
    grad2d: Optional[torch.Tensor] = None  # [N,2] dL/dmeans2d of this view's share of the batch loss
    means_grad: Optional[torch.Tensor] = None  # its share of dL/dmeans, when the op gives no means2d (surfels)
    loss: float = 0.0
    values: Dict[str, float] = field(default_factory=dict)
    psnr: Optional[float] = None


def scalar_names(passes: Sequence[ViewPass]) -> List[str]:
    """The per-term names, in one order every rank shares (the terms are the same on all ranks)."""
    return sorted(passes[0].values) if passes else []


def local_sums(passes: Sequence[ViewPass], names: Sequence[str]) -> List[float]:
    """[loss sum, PSNR sum, views with a PSNR, one sum per term] of this rank's views."""
    psnrs = [p.psnr for p in passes if p.psnr is not None]
    return ([sum(p.loss for p in passes), sum(psnrs), float(len(psnrs))]
            + [sum(p.values[n] for p in passes) for n in names])


def batch_summary(sums: Sequence[float], names: Sequence[str], total_views: int) -> dict:
    """{"loss", "values", "psnr"}: means over the whole batch, from the summed local_sums."""
    loss, psnr_sum, psnr_count = sums[0], sums[1], sums[2]
    return {"loss": loss / total_views, "values": {n: v / total_views for n, v in zip(names, sums[3:])},
            "psnr": psnr_sum / psnr_count if psnr_count else None}


def batch_result(summary: dict, like: LossResult) -> LossResult:
    """The batch's mean losses as a LossResult on `like`'s device, for the NaN guard (a NaN in any view makes the
    mean NaN)."""
    device = like.total.device
    return LossResult(total=torch.tensor(summary["loss"], device=device),
                      values={n: torch.tensor(v, device=device) for n, v in summary["values"].items()},
                      weights=dict(like.weights))
