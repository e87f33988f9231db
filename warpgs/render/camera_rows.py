"""One copy of the camera per Gaussian for the projection adjoint when the camera's gradient is wanted.

The generated adjoint adds every Gaussian's share of d(loss)/d(viewmat, intrinsics) into the one camera's gradient
with atomics, and at a million Gaussians they all queue on the same 20 floats: 25.4 ms on an H200 against 0.95 ms
for the stage without the camera (benchmarks/project_adjoint.py --camera-grads). Given [N] copies, each Gaussian
reads and adds into its own row (kernels/project.py indexes the camera by Gaussian when given N); torch sums them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch


@dataclass
class CameraRows:
    viewmat: torch.Tensor  # [N, 4, 4] copies of the camera
    intrinsics: torch.Tensor  # [N, 4]
    g_viewmat: Optional[torch.Tensor]  # [N, 4, 4] zeros the adjoint adds into (None: not wanted)
    g_intrinsics: Optional[torch.Tensor]  # [N, 4]

    def add_into(self, g_viewmat: Optional[torch.Tensor], g_intrinsics: Optional[torch.Tensor]) -> None:
        """Adds the rows' sums into the op's camera gradients (any shape holding 16 and 4 values)."""
        for rows, grad in ((self.g_viewmat, g_viewmat), (self.g_intrinsics, g_intrinsics)):
            if rows is not None and grad is not None:
                grad.view(-1).add_(rows.sum(0).view(-1))


def camera_rows(n: int, viewmat: torch.Tensor, intrinsics: torch.Tensor, want_viewmat: bool,
                want_intrinsics: bool) -> CameraRows:
    """Copies of one camera ([1, 4, 4] / [4, 4] and [1, 4] / [4]) for `n` Gaussians, with zeroed gradient rows."""
    view = viewmat.reshape(1, 4, 4).expand(n, 4, 4).contiguous()
    intr = intrinsics.reshape(1, 4).expand(n, 4).contiguous()
    return CameraRows(view, intr, torch.zeros_like(view) if want_viewmat else None,
                      torch.zeros_like(intr) if want_intrinsics else None)
