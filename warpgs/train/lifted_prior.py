"""Points lifted from a scene's depth priors: the dense 2.5D sketch as 3D points, shared by the initial model's
prior points (setup.py, model.prior_points) and the virtual views' point cloud (virtual_views.py)."""
from __future__ import annotations

from warpgs.train.few_views import FewViewsRule

# model.prior_points_confidence=auto: AUTO_FEW with at most AUTO_FEW_MAX_VIEWS training views, else AUTO_MANY. The
# plane sweep's confidence scales with the share of a pixel's neighbours that agree, and views all around a scene see
# less of each other than a few forward-facing ones: at 24 views of bonsai800 3% of the pixels reach 0.8 (LLFF's 3
# views: 7-21%), and the points crowd into the few places that do. Measured, 0.5 against 0.8 (docs/sparse_view.md):
# 24 views around bonsai800 +0.29 +- 0.13 dB, phone64 at 16 / 20 / 24 views +0.27 / +0.35 / +0.10 (H200, 3 seeds);
# 12 views of phone64 a tie (-0.17 +- 0.08 at 3000 steps, +0.05 +- 0.20 at 10k); 9 views of a real light field -0.11
# and 3 views of 4 real LLFF scenes -0.16 in the mean (CPU, seed 0). The bound sits in the tie, between 9 and 16.
AUTO_FEW = 0.8
AUTO_MANY = 0.5
AUTO_FEW_MAX_VIEWS = 9
RULE = FewViewsRule("prior points' confidence", "model.prior_points_confidence", AUTO_FEW_MAX_VIEWS, AUTO_FEW,
                    more=AUTO_MANY)


def confidence_for(setting, num_train_views: int) -> float:
    """The least prior confidence model.prior_points_confidence asks for with this many training views."""
    return RULE.value(setting, num_train_views, float)


def lifted_prior(scene, views, n: int, min_confidence: float, seed: int, key: str, named: str):
    """A PointCloud of n pixels of the views' depth priors of at least min_confidence, lifted with their colours
    (init_points.points_from_depth). Errors name the config `key` (shown as `named`): a scene without priors, or no
    pixel that confident."""
    from warpgs.data.sfm import init_points as ip

    if not scene.has("depth_prior", views):
        raise ValueError(f"{named}: the scene at {scene.root} has no depth priors for its training views (set "
                         f"data.depth_priors, e.g. 'estimate', or {key}=0)")
    try:
        return ip.points_from_depth(scene, n=n, views=views, source="prior", seed=seed, min_confidence=min_confidence)
    except ValueError:
        raise ValueError(f"{key}: no training-view prior pixel has confidence >= {min_confidence} (lower "
                         f"model.prior_points_confidence)") from None
