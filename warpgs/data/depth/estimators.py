"""The depth-estimator interface. Implementations: plane_sweep.PlaneSweepStereo (built in, no weights) and
video_depth.VideoDepthAnything (optional adapter for a learned video depth model run over a pseudo-video)."""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

# Name of the EXR channel a written prior keeps its confidence in (read back by Scene.prior_confidence_np).
CONFIDENCE_CHANNEL = "confidence"


@dataclass
class DepthEstimate:
    inv_depth: np.ndarray  # [H, W] float32 at the served resolution of the view
    valid: np.ndarray  # [H, W] bool
    metric: bool  # True: in scene units already (stereo); False: up to scale and shift (monocular/video)
    confidence: Optional[np.ndarray] = None  # [H, W] float32 in [0, 1], higher is better


class DepthEstimator(ABC):
    name: str = "estimator"

    @abstractmethod
    def estimate(self, scene, views: Sequence[int], sources: Optional[Sequence[int]] = None) -> dict[int, DepthEstimate]:
        """Inverse depth for each view index in `views`; `sources` are the views it may use as evidence
        (default: the scene's training views), so test views never leak into training priors."""
