"""SSIM as a torch op over Warp kernels (kernels/ssim.py): the same value as warpgs.metrics.image.ssim (to float32
rounding) in five launches, differentiable in the prediction. The trainer hands it to the D-SSIM loss on a GPU
(`train.fused_ssim`), where torch's filtering is slow at high resolution and launch-bound at low.

The target is data: no gradient flows to it (a target that requires grad is refused).
"""
from __future__ import annotations

import threading

import torch
import warp as wp

from warpgs.kernels import ssim as kernels
from warpgs.metrics.image import _SSIM_EPS, _pair, ssim_window
from warpgs.render.differentiable_once import differentiable_once
from warpgs.render.torch_streams import on_torch_stream, warp_device
from warpgs.render.workspace import LaunchCache


def fused_ssim(pred: torch.Tensor, target: torch.Tensor, window_size: int = 11, max_val: float = 1.0) -> torch.Tensor:
    """Mean SSIM of [H,W,C] or [B,H,W,C] images (C 1 or 3), 11x11 Gaussian window (sigma 1.5), reflection padding."""
    if target.requires_grad:
        raise ValueError("target: fused_ssim differentiates the prediction only; pass target.detach()")
    pred, target = _pair(pred, target)
    if pred.dtype != torch.float32:
        raise ValueError(f"pred: fused_ssim takes float32 images, got {pred.dtype}")
    window = ssim_window(window_size, pred.shape[1], pred.shape[2], pred.device, pred.dtype).reshape(-1).contiguous()
    return _FusedSSIM.apply(pred, target, window, float(max_val)).mean()


def _desc(t: torch.Tensor, dtype=wp.float32):
    """A bare array descriptor (cheaper than a wp.array) of a contiguous tensor, flat unless dtype is a vector."""
    if dtype is wp.float32:
        t = t.reshape(-1)
    return wp.from_torch(t, dtype=dtype, requires_grad=False, return_ctype=True)


_CACHES = threading.local()


def _launches(device: torch.device) -> LaunchCache:
    """This thread's recorded launches on `device`: a call re-packs only the arguments that changed (the render op's
    LaunchCache), which is most of a small image's cost."""
    by_device = getattr(_CACHES, "by_device", None)
    if by_device is None:
        by_device = _CACHES.by_device = {}
    cache = by_device.get(device)
    if cache is None:
        cache = by_device[device] = LaunchCache(warp_device(device))
    return cache


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, target, window, max_val):
        b, h, w, c = pred.shape
        n = pred.numel()
        c1, c2 = (0.01 * max_val) ** 2, (0.03 * max_val) ** 2
        x, y = pred.detach().contiguous(), target.contiguous()
        along_w = torch.empty(n, 5, device=pred.device, dtype=torch.float32)
        means = torch.empty_like(along_w)
        out = torch.empty_like(x)
        run = _launches(pred.device).launch
        with on_torch_stream(pred.device):
            ww, wmeans, weights = _desc(along_w, kernels.Moments), _desc(means, kernels.Moments), _desc(window)
            run("ssim_blur_w", kernels.blur_moments_along_w, n, [_desc(x), _desc(y), weights, w, c, ww])
            run("ssim_blur_h", kernels.blur_along_h_to_ssim, n,
                [ww, weights, h, w * c, c1, c2, _SSIM_EPS, wmeans, _desc(out)])
        ctx.save_for_backward(x, y, window, means)
        ctx.consts = (c1, c2)
        return out

    @staticmethod
    @differentiable_once("the Warp SSIM (train.fused_ssim)")
    def backward(ctx, grad_map):
        x, y, window, means = ctx.saved_tensors
        c1, c2 = ctx.consts
        b, h, w, c = x.shape
        n = x.numel()
        moment_grads = torch.empty(n, 3, device=x.device, dtype=torch.float32)
        along_h = torch.empty_like(moment_grads)
        grad = torch.empty_like(x)
        upstream = grad_map.contiguous()  # the mean's gradient arrives expanded (stride 0)
        run = _launches(x.device).launch
        with on_torch_stream(x.device):
            wg, wh, weights = _desc(moment_grads, kernels.MomentGrads), _desc(along_h, kernels.MomentGrads), _desc(window)
            run("ssim_map_adjoint", kernels.ssim_map_adjoint, n,
                [_desc(means, kernels.Moments), _desc(upstream), c1, c2, _SSIM_EPS, wg])
            run("ssim_adjoint_h", kernels.blur_adjoint_along_h, n, [wg, weights, h, w * c, wh])
            run("ssim_input_grad", kernels.input_grad_along_w, n, [wh, weights, w, c, _desc(x), _desc(y), _desc(grad)])
        return grad, None, None, None
