"""Bookkeeping of one step over a batch of views: what each view's render and backward leave behind (ViewPass),
and the batch's loss, per-term values and train PSNR from the per-view sums (summed over ranks when distributed).

The render op takes one camera, so a batch is rendered one view at a time: render, loss / B, backward, then the
next view. Gradients accumulate in .grad as the mean over the batch, and only one view's render buffers are alive
at a time (the fast GPU path also reuses its workspace between calls, so a view's backward must come before the
next view's render)."""
from __future__ import annotations

import math
from dataclasses import dataclass, is_dataclass, replace
from typing import Dict, List, Optional, Sequence

import torch

from warpgs.losses.registry import LossResult
from warpgs.train.step_info import HostCopy


class HostScalars:
    """A view's loss, per-term values and image MSE on their way to the host. On a GPU the copy starts without
    waiting (into pinned memory, with an event) and is read when first asked for: the training loop asks a step
    later (train/step_info.py), when the copy is done, so the step never waits for its own backward (a wait left
    the GPU idle while the host issued the next launches). On the CPU the values are there at once."""

    def __init__(self, result: LossResult, rgb: Optional[torch.Tensor] = None, image: Optional[torch.Tensor] = None):
        self.names = list(result.values)
        scalars = [result.total.detach().reshape(())] + [result.values[k].detach().reshape(()) for k in self.names]
        self.has_mse = rgb is not None
        if self.has_mse:  # read now: the next view's render may reuse the output buffers
            scalars.append(((rgb.detach() - image) ** 2).mean())
        self._copy = HostCopy(torch.stack([v.float() for v in scalars]))

    def summary(self) -> dict:
        """{"loss": total, "values": {term: value}, "psnr": of the render, or None without an image}."""
        host = self.read()
        psnr = 10.0 * math.log10(1.0 / max(host[-1], 1e-10)) if self.has_mse else None
        return {"loss": host[0], "values": dict(zip(self.names, host[1:1 + len(self.names)])), "psnr": psnr}

    def ready(self) -> bool:
        """Whether read() would return at once."""
        return self._copy.ready()

    def read(self) -> List[float]:
        """[total, one value per term, (image MSE)] as Python floats (waits for the copy the first time)."""
        return self._copy.read()


def without_graph(result: LossResult) -> LossResult:
    """A view's losses after its backward, without their autograd graph: the step keeps them (the NaN guard, the
    log) past the next view's render, and a graph held that long keeps its nodes and whatever their contexts hold."""
    return replace(result, total=result.total.detach()) if is_dataclass(result) else result


@dataclass
class ViewPass:
    """One view of the step, after its backward. loss, values and psnr are read from `scalars` when first used."""
    view: object
    result: LossResult  # this view's losses (total not divided by the batch size)
    scalars: HostScalars
    visible: Optional[torch.Tensor] = None  # [N] bool, when densifying
    grad2d: Optional[torch.Tensor] = None  # [N,2] dL/dmeans2d of this view's share of the batch loss
    means_grad: Optional[torch.Tensor] = None  # its share of dL/dmeans, when the op gives no means2d (surfels)
    pairs_overflowed: Optional[torch.Tensor] = None  # its render's flag (speculative_pairs): skip the step when 1

    @property
    def loss(self) -> float:
        return self.scalars.summary()["loss"]

    @property
    def values(self) -> Dict[str, float]:
        return self.scalars.summary()["values"]

    @property
    def psnr(self) -> Optional[float]:
        return self.scalars.summary()["psnr"]


def scalar_names(passes: Sequence[ViewPass]) -> List[str]:
    """The per-term names, in one order every rank shares (the terms are the same on all ranks)."""
    return sorted(passes[0].scalars.names) if passes else []  # the names only: the values may still be on the way


def local_sums(passes: Sequence[ViewPass], names: Sequence[str]) -> List[float]:
    """[loss sum, PSNR sum, views with a PSNR, one sum per term] of this rank's views."""
    return summary_sums([p.scalars.summary() for p in passes], names)


def summary_sums(parts: Sequence[dict], names: Sequence[str]) -> List[float]:
    """local_sums of views' summaries (HostScalars.summary)."""
    psnrs = [p["psnr"] for p in parts if p["psnr"] is not None]
    return ([sum(p["loss"] for p in parts), sum(psnrs), float(len(psnrs))]
            + [sum(p["values"][n] for p in parts) for n in names])


def batch_summary(sums: Sequence[float], names: Sequence[str], total_views: int) -> dict:
    """{"loss", "values", "psnr"}: means over the whole batch, from the summed local_sums."""
    loss, psnr_sum, psnr_count = sums[0], sums[1], sums[2]
    return {"loss": loss / total_views, "values": {n: v / total_views for n, v in zip(names, sums[3:])},
            "psnr": psnr_sum / psnr_count if psnr_count else None}


class BatchScalars:
    """A single process's batch summary (batch_summary of its views' sums), read from the views' HostScalars on first
    use: like one view's, it need not wait for the backward."""

    def __init__(self, passes: Sequence[ViewPass], names: Sequence[str], total_views: int):
        self.scalars = [p.scalars for p in passes]  # not the passes: their buffers should not outlive the step
        self.names, self.total_views = list(names), int(total_views)

    def ready(self) -> bool:
        return all(s.ready() for s in self.scalars)

    def summary(self) -> dict:
        return batch_summary(summary_sums([s.summary() for s in self.scalars], self.names), self.names,
                             self.total_views)


def device_batch_result(passes: Sequence[ViewPass], total_views: int) -> LossResult:
    """The batch's mean losses as device tensors (the views' sums / total_views), for the NaN guard without a host
    read (a NaN in any view makes the mean NaN)."""
    like = passes[0].result
    total = torch.stack([p.result.total.detach().reshape(()) for p in passes]).sum() / total_views
    values = {n: torch.stack([p.result.values[n].detach().reshape(()) for p in passes]).sum() / total_views
              for n in like.values}
    return LossResult(total=total, values=values, weights=dict(like.weights))


def batch_result(summary: dict, like: LossResult) -> LossResult:
    """The batch's mean losses as a LossResult on `like`'s device, for the NaN guard (a NaN in any view makes the
    mean NaN)."""
    device = like.total.device
    return LossResult(total=torch.tensor(summary["loss"], device=device),
                      values={n: torch.tensor(v, device=device) for n, v in summary["values"].items()},
                      weights=dict(like.weights))
