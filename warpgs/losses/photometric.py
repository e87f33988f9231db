"""Photometric terms of 3DGS: 0.8 L1 + 0.2 D-SSIM against batch["image"] ([H,W,3] or [B,H,W,3] in [0,1]).

D-SSIM here is 1 - SSIM, as in the 3DGS paper and code. (kornia.losses.ssim_loss returns (1 - SSIM) / 2,
which would halve the term, so it is not used.)
"""
from __future__ import annotations

import torch

from warpgs.losses.cuda_graphs import ShapeGraphs
from warpgs.losses.registry import batch_field, register_loss, render_output
from warpgs.metrics.image import ssim

# On a GPU, a training step's torch SSIM replays from a CUDA graph (cuda_graphs.py: it is launch-bound there).
_graphed_ssim = ShapeGraphs(ssim)
_installed_ssim = None


def use_training_ssim(fn=None) -> None:
    """The SSIM the D-SSIM term differentiates, fn(pred, target) -> mean SSIM, replayed from CUDA graphs in a
    GPU training step like torch's (a Warp op is host-bound there too); None: torch's (metrics.image.ssim).
    The trainer installs the Warp-fused one (render/ssim_op.py) per `train.fused_ssim`; it is a process-wide
    choice (losses take no render settings), the last trainer built sets it."""
    global _installed_ssim
    _installed_ssim = None if fn is None else ShapeGraphs(fn)


def training_ssim(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (_installed_ssim or _graphed_ssim)(pred, target)

IMAGE_KEY = "image"


def _pred_and_target(render_out, batch):
    pred = render_output(render_out, "rgb")
    target = batch_field(batch, IMAGE_KEY).to(pred)
    if pred.shape != target.shape:
        raise ValueError(f"batch.{IMAGE_KEY}: shape {list(target.shape)} does not match the render {list(pred.shape)}")
    return pred, target


@register_loss("l1", outputs=("rgb",), weight=0.8)
def l1(render_out, batch, model, step) -> torch.Tensor:
    pred, target = _pred_and_target(render_out, batch)
    return (pred - target).abs().mean()


@register_loss("dssim", outputs=("rgb",), weight=0.2)
def dssim(render_out, batch, model, step) -> torch.Tensor:
    pred, target = _pred_and_target(render_out, batch)
    return 1.0 - training_ssim(pred, target)
