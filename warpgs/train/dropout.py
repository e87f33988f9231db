"""Dropout of primitives in training renders (`train.drop_rate`; DropGaussian, Park et al., CVPR 2025): each
training view renders with every primitive kept with probability 1 - r, the kept ones' opacities divided by 1 - r
so that a pixel's expected coverage is unchanged. With few views a model fits them with many small primitives that
only work together; renders that miss a random tenth of them make each primitive fit the images on its own.
Evaluation and every output render the whole model."""
from __future__ import annotations

import torch


def dropped_opacities(opacities: torch.Tensor, rate: float) -> torch.Tensor:
    """Opacities [N] or [N, 1] with a random share `rate` of the rows zeroed and the rest divided by 1 - rate
    (differentiable; the kept rows' gradients scaled alike). rate 0: `opacities` itself."""
    if rate <= 0.0:
        return opacities
    keep = torch.rand(opacities.shape[0], device=opacities.device) >= rate
    scale = keep.to(opacities.dtype) * (1.0 / (1.0 - rate))
    return opacities * scale.view((-1,) + (1,) * (opacities.dim() - 1))
