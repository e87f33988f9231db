"""Dropout of primitives in training renders (`train.drop_rate`; DropGaussian, Park et al., CVPR 2025): each
training view renders with every primitive kept with probability 1 - r, the kept ones' opacities divided by 1 - r
so that a pixel's expected coverage is unchanged. With few views a model fits them with many small primitives that
only work together; renders that miss a random tenth of them make each primitive fit the images on its own.
Evaluation and every output render the whole model."""
from __future__ import annotations

import torch

from warpgs.train.few_views import FewViewsRule

# train.drop_rate=auto: AUTO_RATE with at most AUTO_MAX_VIEWS training views, else off. Measured (docs/sparse_view.md):
# 3 views +0.22 dB over 7 LLFF scenes (3 seeds), 4 views +0.11 (one seed); 9 views of a real light field -1.52 and
# 24 views around a 360° capture -0.16 (CPU). Between 4 and 9 views it is unmeasured, so auto leaves it off there.
AUTO_RATE = 0.1
AUTO_MAX_VIEWS = 4
RULE = FewViewsRule("primitive dropout", "drop_rate", AUTO_MAX_VIEWS, AUTO_RATE)


def drop_rate_for(setting, num_train_views: int) -> float:
    """The dropout rate that train.drop_rate asks for with this many training views."""
    return RULE.value(setting, num_train_views, float)


def dropout_note(setting, rate: float, num_train_views: int) -> str:
    """The start line's words on dropout: its rate when on, why not when "auto" left it off, else ""."""
    return RULE.note(setting, rate, num_train_views, f"; primitive dropout {rate:g}")


def dropped_opacities(opacities: torch.Tensor, rate: float) -> torch.Tensor:
    """Opacities [N] or [N, 1] with a random share `rate` of the rows zeroed and the rest divided by 1 - rate
    (differentiable; the kept rows' gradients scaled alike). rate 0: `opacities` itself."""
    if rate <= 0.0:
        return opacities
    keep = torch.rand(opacities.shape[0], device=opacities.device) >= rate
    scale = keep.to(opacities.dtype) * (1.0 / (1.0 - rate))
    return opacities * scale.view((-1,) + (1,) * (opacities.dim() - 1))
