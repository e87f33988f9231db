"""Make the 2.5D sketch: estimate inverse depth per view, align it to the SfM points, write it as EXR."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from warpgs.data.depth.align import align_depth_to_points
from warpgs.data.depth.estimators import DepthEstimator
from warpgs.data.depth.files import write_exr
from warpgs.data.scene import MapFormat, Scene
from warpgs.data.formats.view_files import write_map_format

PRIOR_FOLDER = "depth_priors"


def compute_depth_priors(scene: Scene, estimator: Optional[DepthEstimator] = None, *,
                         views: Optional[Sequence[int]] = None, out_dir: Optional[Path] = None,
                         align: bool = True, min_points: int = 10) -> tuple[Scene, dict]:
    """Estimate, align and write priors for `views` (default: training views) into out_dir (default
    <scene root>/depth_priors). Returns the scene with priors attached and a report:
    {"estimator", "seconds", "views": {name: {"alignment": {...} or None, "valid_fraction"}}}.

    Relative (non-metric) estimates must be aligned, so they need SfM points; metric ones (stereo) are aligned
    too when points exist, and the report's scale/shift then shows how well they already agreed.
    """
    from warpgs.data.depth.plane_sweep import PlaneSweepStereo

    estimator = estimator or PlaneSweepStereo()
    views = list(scene.train if views is None else views)
    out_dir = Path(out_dir) if out_dir is not None else scene.root / PRIOR_FOLDER
    start = time.perf_counter()
    estimates = estimator.estimate(scene, views)
    report = {"estimator": estimator.name, "views": {}}
    for v in views:
        est = estimates[v]
        inv, valid = est.inv_depth.astype(np.float64), est.valid.copy()
        alignment = None
        seen = scene.visible_points(v)
        if align and scene.points is not None and len(seen) >= min_points:
            alignment = align_depth_to_points(inv, valid, scene.cameras[v], scene.points.xyz[seen])
            inv = alignment.apply(inv)
            valid &= inv > 0
        elif not est.metric:
            raise ValueError(f"view {scene.names[v]!r}: a relative depth estimate needs at least {min_points} "
                             f"SfM points to align to, the view sees {len(seen)}")
        write_exr(out_dir / f"{Path(scene.names[v]).stem}.exr", np.where(valid, inv, 0.0), "inverse_depth", valid)
        report["views"][scene.names[v]] = {"alignment": None if alignment is None else alignment.as_dict(),
                                           "valid_fraction": float(valid.mean())}
    report["seconds"] = round(time.perf_counter() - start, 3)
    write_map_format(out_dir, MapFormat("inverse_depth"), estimator=estimator.name, aligned=align,
                     views=report["views"])
    return scene.with_depth_priors(out_dir, MapFormat("inverse_depth")), report
