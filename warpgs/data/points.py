"""Sparse 3D points (SfM or sampled from surfaces) and the views that observe them."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch


@dataclass(eq=False)
class PointCloud:
    xyz: np.ndarray  # [N, 3] float32 world coordinates
    rgb: np.ndarray  # [N, 3] float32 in [0, 1]
    # For each scene view, indices of the points it observes (SfM tracks); None when tracks are unknown.
    observed_by: Optional[list] = None

    def __post_init__(self):
        self.xyz = np.asarray(self.xyz, dtype=np.float32).reshape(-1, 3)
        self.rgb = np.asarray(self.rgb, dtype=np.float32).reshape(-1, 3)
        if len(self.xyz) != len(self.rgb):
            raise ValueError(f"points: {len(self.xyz)} positions but {len(self.rgb)} colours")
        if not np.all(np.isfinite(self.xyz)):
            raise ValueError("points: positions must be finite")
        if self.observed_by is not None:
            self.observed_by = [np.asarray(v, dtype=np.int64) for v in self.observed_by]

    def __len__(self) -> int:
        return len(self.xyz)

    def tensors(self, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.as_tensor(self.xyz, device=device), torch.as_tensor(self.rgb, device=device)
