"""Image quality metrics: PSNR, SSIM (kornia) and LPIPS when it is available offline.

Images are [H,W,3] or [B,H,W,3] floats in [0,1]. LPIPS is never downloaded: it is used only when the
`lpips` package is importable and both its linear-layer weights and the torchvision backbone weights are
already on disk; otherwise `LPIPSMetric.available` is False and `reason` says why.
"""
from __future__ import annotations

import functools
import importlib.util
import os
from typing import Optional

import torch
from kornia.filters import filter2d_separable, get_gaussian_kernel1d

# torchvision checkpoint files the lpips backbones load from the torch hub cache.
_BACKBONE_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth",
                   "squeeze": "squeezenet1_1-b8a52dc0.pth"}


def _pair(pred: torch.Tensor, target: torch.Tensor):
    if not (torch.is_tensor(pred) and torch.is_tensor(target)):
        raise ValueError("pred/target: expected torch tensors")
    if pred.shape != target.shape:
        raise ValueError(f"pred/target: shapes differ, {list(pred.shape)} vs {list(target.shape)}")
    if pred.dim() not in (3, 4) or pred.shape[-1] not in (1, 3):
        raise ValueError(f"pred: expected [H,W,C] or [B,H,W,C] with C in (1, 3), got {list(pred.shape)}")
    if pred.dim() == 3:
        pred, target = pred[None], target[None]
    return pred, target.to(pred)


def to_bchw(img: torch.Tensor) -> torch.Tensor:
    return img.permute(0, 3, 1, 2)


def psnr(pred: torch.Tensor, target: torch.Tensor, max_val: float = 1.0) -> torch.Tensor:
    """Mean over images of 10 log10(max_val^2 / MSE). MSE is floored at 1e-10 so identical images give a
    finite 100 dB (for max_val 1) instead of inf, which JSON cannot hold."""
    pred, target = _pair(pred, target)
    mse = ((pred - target) ** 2).flatten(1).mean(1).clamp_min(1e-10)
    return (10.0 * torch.log10(max_val ** 2 / mse)).mean()


def ssim(pred: torch.Tensor, target: torch.Tensor, window_size: int = 11, max_val: float = 1.0) -> torch.Tensor:
    """Mean SSIM with an 11x11 Gaussian window (sigma 1.5) as 3DGS; reflection padding (kornia's), where 3DGS pads
    with zeros, so values differ slightly within 5 px of the border. Differentiable (the D-SSIM loss uses it).

    The same formula as kornia.metrics.ssim (tests/test_metrics.py compares them), but the five local means go
    through one separable filtering of the stacked channels with a cached window, not five: a training step's
    SSIM is then about a dozen kernels instead of about sixty, which is host time on a GPU."""
    pred, target = _pair(pred, target)
    x, y = to_bchw(pred), to_bchw(target)
    window = ssim_window(window_size, pred.shape[1], pred.shape[2], x.device, x.dtype)
    local = filter2d_separable(torch.cat([x, y, x * x, y * y, x * y], 1), window, window, border_type="reflect")
    mu_x, mu_y, xx, yy, xy = local.chunk(5, 1)
    c1, c2 = (0.01 * max_val) ** 2, (0.03 * max_val) ** 2
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    num = (2.0 * mu_xy + c1) * (2.0 * (xy - mu_xy) + c2)
    den = (mu_xx + mu_yy + c1) * ((xx - mu_xx) + (yy - mu_yy) + c2)
    return (num / (den + _SSIM_EPS)).mean()


_SSIM_EPS = 1e-12  # kornia.metrics.ssim's default


def ssim_window(window_size: int, height: int, width: int, device, dtype) -> torch.Tensor:
    """The [1, size] window SSIM filters an image of height x width with: reflection padding needs
    size // 2 < min(H, W), so tiny images get a smaller one."""
    return _gaussian_window(min(int(window_size), 2 * min(height, width) - 1), device, dtype)


@functools.lru_cache(maxsize=32)
def _gaussian_window(size: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """[1, size] normalised Gaussian, sigma 1.5 (kornia's own window for SSIM); built once per size and device, never
    as an inference tensor (a first SSIM under inference_mode would otherwise break every differentiated one after)."""
    with torch.inference_mode(False):
        return get_gaussian_kernel1d(size, 1.5, device=device, dtype=dtype)


def lpips_unavailable_reason(net: str = "alex") -> Optional[str]:
    """None if LPIPS(net) can be built from local files only, else why not."""
    if net not in _BACKBONE_FILES:
        return f"net: expected one of {sorted(_BACKBONE_FILES)}, got {net!r}"
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        return "the 'lpips' package is not installed"
    package_dir = list(spec.submodule_search_locations)[0]
    linear = os.path.join(package_dir, "weights", "v0.1", f"{net}.pth")
    if not os.path.isfile(linear):
        return f"lpips linear weights not found at {linear}"
    backbone = os.path.join(torch.hub.get_dir(), "checkpoints", _BACKBONE_FILES[net])
    if not os.path.isfile(backbone):
        return f"backbone weights not cached at {backbone} (not downloaded on purpose)"
    return None


class LPIPSMetric:
    """Callable (pred, target) -> mean LPIPS tensor, or None when unavailable (see `reason`)."""

    def __init__(self, net: str = "alex", device="cpu"):
        self.net, self.model = net, None
        self.reason = lpips_unavailable_reason(net)
        if self.reason is None:
            try:
                import lpips

                self.model = lpips.LPIPS(net=net, verbose=False).to(device).eval()
            except Exception as e:  # a broken install must not stop training or evaluation
                self.reason = f"lpips failed to load: {type(e).__name__}: {e}"

    @property
    def available(self) -> bool:
        return self.model is not None

    @torch.no_grad()
    def __call__(self, pred: torch.Tensor, target: torch.Tensor) -> Optional[torch.Tensor]:
        if self.model is None:
            return None
        pred, target = _pair(pred, target)
        device = next(self.model.parameters(), torch.empty(0)).device
        # lpips expects [-1, 1] inputs; normalize=True maps [0, 1] there.
        return self.model(to_bchw(pred).to(device), to_bchw(target).to(device), normalize=True).mean()


def image_metrics(pred: torch.Tensor, target: torch.Tensor, lpips: Optional[LPIPSMetric] = None) -> dict:
    """{"psnr", "ssim", "lpips"} as floats; lpips is None (with "lpips_unavailable": reason) when missing."""
    with torch.no_grad():
        out = {"psnr": float(psnr(pred, target)), "ssim": float(ssim(pred, target))}
        value = lpips(pred, target) if lpips is not None else None
    out["lpips"] = None if value is None else float(value)
    if value is None:
        out["lpips_unavailable"] = lpips.reason if lpips is not None else "not requested"
    return out
