"""SSIM as a torch op over Warp kernels (kernels/ssim.py): the same value as warpgs.metrics.image.ssim (to float32
rounding) in eight launches, differentiable in the prediction. The trainer hands it to the D-SSIM loss on a GPU
(`train.fused_ssim`), where torch's filtering is slow at high resolution and launch-bound at low.

The target is data: no gradient flows to it (a target that requires grad is refused).
"""
from __future__ import annotations

import torch
import warp as wp

from warpgs.kernels import ssim as kernels
from warpgs.metrics.image import _SSIM_EPS, _gaussian_window, _pair
from warpgs.render.torch_streams import on_torch_stream


def fused_ssim(pred: torch.Tensor, target: torch.Tensor, window_size: int = 11, max_val: float = 1.0) -> torch.Tensor:
    """Mean SSIM of [H,W,C] or [B,H,W,C] images (C 1 or 3), 11x11 Gaussian window (sigma 1.5), reflection padding."""
    if target.requires_grad:
        raise ValueError("target: fused_ssim differentiates the prediction only; pass target.detach()")
    pred, target = _pair(pred, target)
    if pred.dtype != torch.float32:
        raise ValueError(f"pred: fused_ssim takes float32 images, got {pred.dtype}")
    window_size = min(int(window_size), 2 * min(pred.shape[1], pred.shape[2]) - 1)
    window = _gaussian_window(window_size, pred.device, pred.dtype).reshape(-1).contiguous()
    return _FusedSSIM.apply(pred, target, window, float(max_val)).mean()


def _flat(t: torch.Tensor, dtype=wp.float32):
    return wp.from_torch(t.contiguous().reshape(-1), dtype=dtype)


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, target, window, max_val):
        b, h, w, c = pred.shape
        n = pred.numel()
        c1, c2 = (0.01 * max_val) ** 2, (0.03 * max_val) ** 2
        x, y = pred.detach().contiguous(), target.contiguous()
        blur = kernels.blur_axis_kernel(5)
        moments = torch.empty(n, 5, device=pred.device, dtype=torch.float32)
        along_w = torch.empty_like(moments)
        means = torch.empty_like(moments)
        out = torch.empty_like(x)
        with on_torch_stream(pred.device):
            wm, ww, wmeans = (wp.from_torch(a, dtype=kernels.Moments) for a in (moments, along_w, means))
            weights = wp.from_torch(window)
            wp.launch(kernels.image_moments, dim=n, inputs=[_flat(x), _flat(y)], outputs=[wm])
            wp.launch(blur, dim=n, inputs=[wm, weights, w, c], outputs=[ww])
            wp.launch(blur, dim=n, inputs=[ww, weights, h, w * c], outputs=[wmeans])
            wp.launch(kernels.ssim_map, dim=n, inputs=[wmeans, c1, c2, _SSIM_EPS], outputs=[_flat(out)])
        ctx.save_for_backward(x, y, window, means)
        ctx.consts = (c1, c2)
        return out

    @staticmethod
    def backward(ctx, grad_map):
        x, y, window, means = ctx.saved_tensors
        c1, c2 = ctx.consts
        b, h, w, c = x.shape
        n = x.numel()
        adjoint = kernels.blur_axis_adjoint_kernel(3)
        moment_grads = torch.empty(n, 3, device=x.device, dtype=torch.float32)
        along_h = torch.empty_like(moment_grads)
        along_w = torch.empty_like(moment_grads)
        grad = torch.empty_like(x)
        with on_torch_stream(x.device):
            wg, wh, ww = (wp.from_torch(a, dtype=kernels.MomentGrads) for a in (moment_grads, along_h, along_w))
            weights = wp.from_torch(window)
            wp.launch(kernels.ssim_map_adjoint, dim=n,
                      inputs=[wp.from_torch(means, dtype=kernels.Moments), _flat(grad_map), c1, c2, _SSIM_EPS],
                      outputs=[wg])
            wp.launch(adjoint, dim=n, inputs=[wg, weights, h, w * c], outputs=[wh])
            wp.launch(adjoint, dim=n, inputs=[wh, weights, w, c], outputs=[ww])
            wp.launch(kernels.ssim_input_grad, dim=n, inputs=[ww, _flat(x), _flat(y)], outputs=[_flat(grad)])
        return grad, None, None, None
