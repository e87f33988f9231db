"""A learned environment map behind the primitives: the `environment` trainer extension.

    extensions: {environment: {degree: 3, lr: 0.01}}

Pixels the primitives leave uncovered show colour(ray direction), a low-order real spherical-harmonics function
of the world-space viewing direction (like a sky at infinity), instead of a constant background:
rgb = Σ wᵢcᵢ + (1 - alpha) env(d). Scenes with sky otherwise fill it with primitives somewhere along the
training rays — often right in front of other cameras, where they haze novel views. The map is an nn.Module
trained with its own Adam group and saved in checkpoints; evaluation and `warpgs-render` composite it too.
"""
from __future__ import annotations

import torch
from torch import nn

from warpgs.train.extensions import Extension, register_extension

# Real SH constants (the same basis as the primitives' colours).
_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
       1.445305721320277, -0.5900435899266435)


def sh_basis(d: torch.Tensor, degree: int) -> torch.Tensor:
    """[..., 3] unit directions -> [..., (degree+1)^2] real SH values (degree 0..3)."""
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, _C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [_C2[0] * x * y, _C2[1] * y * z, _C2[2] * (2 * zz - xx - yy), _C2[3] * x * z, _C2[4] * (xx - yy)]
    if degree >= 3:
        out += [_C3[0] * y * (3 * xx - yy), _C3[1] * x * y * z, _C3[2] * y * (4 * zz - xx - yy),
                _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy),
                _C3[5] * z * (xx - yy), _C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, -1)


def ray_directions(viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[H, W, 3] world-space unit directions through the pixel centres."""
    u = torch.arange(width, device=K.device, dtype=K.dtype) + 0.5
    v = torch.arange(height, device=K.device, dtype=K.dtype) + 0.5
    x = ((u[None, :] - K[0, 2]) / K[0, 0]).expand(height, width)
    y = ((v[:, None] - K[1, 2]) / K[1, 1]).expand(height, width)
    d = torch.stack([x, y, torch.ones_like(x)], -1) @ viewmat[:3, :3].to(K)  # R^T d, row-wise
    return d / d.norm(dim=-1, keepdim=True)


class EnvironmentMap(nn.Module):
    def __init__(self, degree: int = 3, init_color: float = 0.5):
        super().__init__()
        if not 0 <= int(degree) <= 3:
            raise ValueError(f"extensions.environment.degree: expected 0..3, got {degree}")
        self.degree = int(degree)
        coeffs = torch.zeros((self.degree + 1) ** 2, 3)
        coeffs[0] = (float(init_color) - 0.5) / _C0
        self.coeffs = nn.Parameter(coeffs)

    def forward(self, dirs: torch.Tensor) -> torch.Tensor:
        return (sh_basis(dirs, self.degree) @ self.coeffs + 0.5).clamp_min(0.0)


@register_extension("environment")
class Environment(Extension):
    def __init__(self, degree: int = 3, lr: float = 0.01, init_color: float = 0.5):
        self.degree, self.lr, self.init_color = int(degree), float(lr), float(init_color)
        self._dirs = {}

    def setup(self, trainer) -> None:
        trainer.add_module("environment", EnvironmentMap(self.degree, self.init_color), lr=self.lr)
        trainer.background = torch.zeros(3, device=trainer.device)  # the map replaces the constant background

    def outputs(self):
        return ("alpha",)

    def after_render(self, trainer, out, batch: dict, step: int):
        if out.rgb is None or out.alpha is None:
            return out
        env = trainer.modules["environment"](self._directions(batch))
        out.rgb = out.rgb + (1.0 - out.alpha) * env
        return out

    def _directions(self, batch: dict) -> torch.Tensor:
        """The view's ray directions, kept per camera. Keyed by the camera tensors' identity and version, not their
        values: reading the values is a host read (a stall on a GPU) every step; a view keeps its tensors for the
        run. The entry holds them, so an id is never another tensor's."""
        W, H = int(batch["width"]), int(batch["height"])
        viewmat, K = batch["viewmat"], batch["K"]
        if torch.is_inference_mode_enabled() or viewmat.is_inference() or K.is_inference():
            return ray_directions(viewmat, K, W, H)  # inference tensors: no version counter, unfit for training
        key = (id(viewmat), viewmat._version, id(K), K._version, W, H)
        hit = self._dirs.get(key)
        if hit is None or hit[0] is not viewmat or hit[1] is not K:
            if len(self._dirs) > 512:
                self._dirs.clear()
            hit = self._dirs[key] = (viewmat, K, ray_directions(viewmat, K, W, H))
        return hit[2]
