"""Maths on raw primitive parameters: colour <-> SH DC coefficient, quaternion -> rotation matrix."""
from __future__ import annotations

import torch

SH_C0 = 0.28209479177387814


def num_sh_coeffs(degree: int) -> int:
    return (int(degree) + 1) ** 2


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """Colour in [0,1] -> DC coefficient, inverse of the renderer's `SH_C0 * c + 0.5`."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    return sh0 * SH_C0 + 0.5


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N,4] wxyz (any norm; zero -> identity-free but finite) -> [N,3,3]."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*q.shape[:-1], 3, 3)
