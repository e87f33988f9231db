"""Points lifted from a scene's depth priors: the dense 2.5D sketch as 3D points, shared by the initial model's
prior points (setup.py, model.prior_points) and the virtual views' point cloud (virtual_views.py)."""
from __future__ import annotations


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
