"""kornia's normalised first-order Sobel gradient, `spatial_gradient(x, "sobel", 1, normalized=True)`, bit for bit,
with its kernel made once per device and dtype.

kornia builds the kernel from a Python list on every call (`torch.tensor(..., device=x.device)`). On a GPU that is a
host-to-device copy, which torch ends with a stream synchronisation: once a step the host waited there for the render
queued before the loss, and issued the rest of the losses and the backward while the GPU sat idle.
"""
from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from kornia.filters import get_spatial_gradient_kernel2d


@functools.cache  # unbounded: a CUDA graph captured with a kernel keeps pointing at it
def sobel_kernel(device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """[2, 1, 3, 3] conv2d weight: kornia's pair (d/dx, d/dy), the 3x3 Sobel kernels over their absolute sums (8),
    built by kornia once; never an inference tensor (a first call under inference_mode would otherwise break every
    differentiated one after)."""
    with torch.inference_mode(False):
        pair = get_spatial_gradient_kernel2d("sobel", 1, device=device, dtype=dtype)
        return (pair / pair.abs().sum((-2, -1), keepdim=True))[:, None]  # kornia's normalisation (normalized=True)


def sobel_gradient(x: torch.Tensor) -> torch.Tensor:
    """[B, C, H, W] floats -> [B, C, 2, H, W] (d/dx, d/dy), replicated border: kornia's ops on kornia's kernel."""
    b, c, h, w = x.shape
    padded = F.pad(x.reshape(b * c, 1, h, w), [1, 1, 1, 1], "replicate")
    return F.conv2d(padded, sobel_kernel(x.device, x.dtype)).reshape(b, c, 2, h, w)
