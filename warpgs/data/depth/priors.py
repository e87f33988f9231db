"""Make the 2.5D sketch: estimate inverse depth per view, align it to the SfM points, write it as EXR (with the
estimator's per-pixel confidence as a `confidence` channel when it gives one; the depth losses weight by it).

A scene without SfM points (an LLFF few-view run: the capture's own points were made from every view, held-out
ones included) gets points triangulated from its training views' known poses, cached in <out_dir>/points: they
bound the plane sweep's depth range and are what the prior is aligned to."""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from warpgs.data.depth.align import align_depth_to_points
from warpgs.data.depth.estimators import CONFIDENCE_CHANNEL, DepthEstimate, DepthEstimator
from warpgs.data.depth.fill import fill_inverse_depth
from warpgs.data.depth import files as depth_files
from warpgs.data.scene import MapFormat, Scene
from warpgs.data.formats.view_files import write_map_format

PRIOR_FOLDER = "depth_priors"
POINTS_FOLDER = "points"  # inside the prior folder: the training-view triangulation of a scene without points


def prior_key(scene: Scene, views: Sequence[int], estimator: DepthEstimator, fill_confidence: float) -> str:
    """Changes when the views' image files, their cameras at the served resolution, the scene's SfM points (the
    alignment's reference), the estimator's settings or the fill change: the name of a shared prior folder."""
    import hashlib

    from warpgs.data.sfm.triangulate import cache_key

    points = hashlib.sha1(b"" if scene.points is None else np.ascontiguousarray(scene.points.xyz).tobytes())
    settings = {"priors": 1, "estimator": estimator.name, "estimator_settings": estimator_settings(estimator),
                "fill_confidence": float(fill_confidence), "views": [int(v) for v in views],
                "points": points.hexdigest()}
    return cache_key([scene.cameras[v] for v in views], [scene.files[v].image for v in views], settings)


def write_prior(path: Path, inv_depth: np.ndarray, valid: np.ndarray, confidence: Optional[np.ndarray] = None) -> Path:
    """An aligned inverse-depth prior as EXR: value, validity and (optional) confidence in [0, 1] channels."""
    channels = {"Z": np.where(valid, inv_depth, 0.0), depth_files._VALID_CHANNEL: valid}
    if confidence is not None:
        channels[CONFIDENCE_CHANNEL] = np.where(valid, np.clip(confidence, 0.0, 1.0), 0.0)
    return depth_files.write_exr_channels(path, channels, {depth_files._KIND_ATTRIBUTE: "inverse_depth"})


def estimator_settings(estimator: DepthEstimator) -> dict:
    """The estimator's plain settings (numbers, strings, flags), as recorded in the prior folder's format.json: a
    trainer re-estimates when they differ from the estimator it would use now."""
    return {k: v for k, v in sorted(vars(estimator).items())
            if not k.startswith("_") and (v is None or isinstance(v, (bool, int, float, str)))}


def _with_training_points(scene: Scene, out_dir: Path) -> Scene:
    """The scene with points triangulated from its training views; unchanged (with a note) when that fails, so
    an estimator given near/far still runs and one that needs points says so."""
    from warpgs.data.errors import SceneError
    from warpgs.data.sfm.triangulate import triangulate_scene

    try:
        tri = triangulate_scene(scene, out_dir / POINTS_FOLDER, progress=False)
    except (SceneError, RuntimeError, ValueError) as exc:  # pycolmap raises RuntimeError/ValueError
        print(f"depth priors: no SfM points and triangulating the training views failed ({exc})", file=sys.stderr)
        return scene
    return scene.with_points(tri.points)


def _filled(scene: Scene, v: int, inv: np.ndarray, valid: np.ndarray, confidence: Optional[np.ndarray],
            fill_confidence: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The prior with its invalid pixels filled (fill_confidence there), and the share of pixels filled."""
    image = scene.image_np(v)[0]
    inv_filled, filled = fill_inverse_depth(inv, valid, image)
    base = np.ones(valid.shape, np.float32) if confidence is None else confidence
    conf = np.where(filled, np.float32(fill_confidence), np.where(valid, base, 0.0)).astype(np.float32)
    return inv_filled, valid | filled, conf, float(filled.mean())


def _aligned(scene: Scene, v: int, est: DepthEstimate, inv: np.ndarray, valid: np.ndarray, seen: np.ndarray):
    """The view's alignment to the points it sees, or None for a metric estimate whose valid pixels meet too few of
    them to fit one: 12 views around a 360° capture left a view with 2 such points of the 10+ it sees. The sweep's
    depth is in the poses' units already, so it is kept as swept (as for a view that sees fewer than min_points);
    a relative estimate cannot be, and the error names the view."""
    try:
        return align_depth_to_points(inv, valid, scene.cameras[v], scene.points.xyz[seen])
    except ValueError as exc:
        if not est.metric:
            raise ValueError(f"view {scene.names[v]!r}: {exc}") from None
        print(f"depth priors: view {scene.names[v]!r} kept unaligned ({exc})", file=sys.stderr)
        return None


def compute_depth_priors(scene: Scene, estimator: Optional[DepthEstimator] = None, *,
                         views: Optional[Sequence[int]] = None, out_dir: Optional[Path] = None,
                         align: bool = True, min_points: int = 10, triangulate: bool = True,
                         fill_confidence: float = 0.0) -> tuple[Scene, dict]:
    """Estimate, align and write priors for `views` (default: training views) into out_dir (default
    <scene root>/depth_priors). Returns the scene with priors attached and a report:
    {"estimator", "seconds", "views": {name: {"alignment": {...} or None, "valid_fraction"}}}.

    Relative (non-metric) estimates must be aligned, so they need SfM points; metric ones (stereo) are aligned
    too when points exist, and the report's scale/shift then shows how well they already agreed. A scene without
    points gets them from its training views (triangulate=True, see the module doc); the returned scene is the
    one given (without those points), so a trainer still chooses its own initial points.

    fill_confidence > 0 fills the pixels the estimator left invalid from the valid ones (warpgs.data.depth.fill,
    edge-aware harmonic interpolation of inverse depth) and gives them this confidence (valid pixels keep the
    estimator's, or 1); 0 leaves them out, as before.
    """
    if not 0.0 <= fill_confidence <= 1.0:
        raise ValueError(f"fill_confidence: expected a confidence in [0, 1], got {fill_confidence}")
    from warpgs.data.depth.plane_sweep import PlaneSweepStereo

    estimator = estimator or PlaneSweepStereo()
    views = list(scene.train if views is None else views)
    out_dir = Path(out_dir) if out_dir is not None else scene.root / PRIOR_FOLDER
    start = time.perf_counter()
    bare = scene
    if scene.points is None and triangulate:
        scene = _with_training_points(scene, out_dir)
    estimates = estimator.estimate(scene, views)
    report = {"estimator": estimator.name, "views": {}}
    for v in views:
        est = estimates[v]
        inv, valid = est.inv_depth.astype(np.float64), est.valid.copy()
        alignment = None
        seen = scene.visible_points(v)
        if align and scene.points is not None and len(seen) >= min_points:
            alignment = _aligned(scene, v, est, inv, valid, seen)
            if alignment is not None:
                inv = alignment.apply(inv)
                valid &= inv > 0
        elif not est.metric:
            raise ValueError(f"view {scene.names[v]!r}: a relative depth estimate needs at least {min_points} "
                             f"SfM points to align to, the view sees {len(seen)}")
        confidence, filled_fraction = est.confidence, 0.0
        if fill_confidence > 0:
            inv, valid, confidence, filled_fraction = _filled(scene, v, inv, valid, confidence, fill_confidence)
        write_prior(out_dir / f"{Path(scene.names[v]).stem}.exr", inv, valid, confidence)
        report["views"][scene.names[v]] = {"alignment": None if alignment is None else alignment.as_dict(),
                                           "valid_fraction": float(valid.mean()), "filled_fraction": filled_fraction,
                                           "confidence": confidence is not None}
    report["seconds"] = round(time.perf_counter() - start, 3)
    write_map_format(out_dir, MapFormat("inverse_depth"), estimator=estimator.name, aligned=align,
                     estimator_settings=estimator_settings(estimator), fill_confidence=fill_confidence,
                     views=report["views"])
    return bare.with_depth_priors(out_dir, MapFormat("inverse_depth")), report
