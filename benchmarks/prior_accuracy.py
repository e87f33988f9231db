"""Accuracy of the built-in plane-sweep depth prior on a real few-view capture (issue 15).

    python benchmarks/prior_accuracy.py data/fern                       # 3 training views, 1/8 resolution
    python benchmarks/prior_accuracy.py data/fern --estimator legacy,default --n-train 3

The prior is made as a few-view training run makes it: from the training views of the LLFF protocol only (each
view matched against the other training views), bounded by and aligned (scale + shift on inverse depth, as the
depth losses use it) to the points triangulated from those same views' known poses. It is scored against the
scene's own SfM model (sparse/0/points3D.bin, built from *all* views): every point counts in the views whose
track saw it (warpgs.data.depth.reference_points), so hidden points never score a foreground pixel.

Per training view and on average: AbsRel and delta<1.25 of the aligned prior's depth at the reference points on
valid pixels, the share of reference points on valid pixels (point coverage), the share of valid pixels (pixel
coverage), the confidence-weighted AbsRel and AbsRel of the 25 / 50 % most confident points; also the AbsRel
after an oracle alignment to the reference points themselves (the shape error alone).
With --fill, also the pixels the estimator left invalid, filled from the valid ones as data.depth_prior_fill does:
AbsRel and delta<1.25 at the reference points on filled pixels only (few: SfM points lie on texture, and the fill
is mostly textureless walls and floor), and the share of pixels filled.
Estimators: "legacy" (the plane sweep before issue 15), "default" (PlaneSweepStereo()). Writes
benchmarks/results/prior_accuracy_<scene>.json (or $OUT/...).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common import write_json

from warpgs.data import PlaneSweepStereo, align_depth_to_points, align_inverse_depth, load_scene
from warpgs.data.depth.evaluate import point_depth_metrics
from warpgs.data.depth.fill import fill_inverse_depth
from warpgs.data.depth.plane_sweep import LEGACY_SETTINGS
from warpgs.data.depth.reference_points import reference_depth, view_reference_points
from warpgs.data.sfm.triangulate import triangulate_scene

ESTIMATORS = {"legacy": lambda: PlaneSweepStereo(**LEGACY_SETTINGS), "default": PlaneSweepStereo}


def score_fill(scene, v: int, aligned: np.ndarray, valid: np.ndarray, pix: np.ndarray, z: np.ndarray) -> dict:
    """The pixels the estimator left invalid, filled as compute_depth_priors(fill_confidence>0) fills them: AbsRel
    and delta<1.25 at the reference points on those pixels only, their count, and the share of pixels filled."""
    filled_inv, filled = fill_inverse_depth(aligned, valid, scene.image_np(v)[0])
    m = point_depth_metrics(filled_inv, filled, pix, z)
    return {"abs_rel_filled": m["abs_rel"], "delta_1_25_filled": m["delta_1_25"], "n_filled": m["n"],
            "pixel_filled": float(filled.mean())}


def score_view(scene, v: int, est, ref_xyz: np.ndarray, fill: bool = False) -> dict:
    cam = scene.cameras[v]
    inv, valid = est.inv_depth.astype(np.float64), est.valid.copy()
    seen = scene.visible_points(v)
    alignment = align_depth_to_points(inv, valid, cam, scene.points.xyz[seen])
    aligned = alignment.apply(inv)
    valid &= aligned > 0
    pix, z = reference_depth(cam, ref_xyz)
    m = point_depth_metrics(aligned, valid, pix, z, est.confidence)
    # Oracle: the same prior aligned to the reference points it is scored on (what alignment cannot fix).
    col = np.clip(pix[:, 0].astype(int), 0, cam.width - 1)
    row = np.clip(pix[:, 1].astype(int), 0, cam.height - 1)
    on = est.valid[row, col]
    oracle = align_inverse_depth(inv[row, col][on], 1.0 / z[on])
    m_oracle = point_depth_metrics(oracle.apply(inv), est.valid & (oracle.apply(inv) > 0), pix, z)
    return {"view": scene.names[v], "abs_rel": m["abs_rel"], "delta_1_25": m["delta_1_25"], "n": m["n"],
            "point_coverage": m["point_coverage"], "pixel_coverage": float(valid.mean()),
            "abs_rel_weighted": m.get("abs_rel_weighted"), "top": m.get("top"),
            "abs_rel_oracle_align": m_oracle["abs_rel"], "reference_points": int(len(z)),
            "alignment": alignment.as_dict(), **(score_fill(scene, v, aligned, valid, pix, z) if fill else {})}


def mean_of(rows: list[dict], key: str):
    vals = [r[key] for r in rows if r.get(key) is not None and np.isfinite(r[key])]
    return statistics.fmean(vals) if vals else None


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", help="LLFF scene folder with sparse/0/points3D.bin (e.g. data/fern)")
    ap.add_argument("--n-train", type=int, default=3, help="training views (LLFF protocol), default 3")
    ap.add_argument("--downscale", type=int, default=8, help="image downscale (default 8: images_8)")
    ap.add_argument("--estimator", default="legacy,default", help="comma-separated: " + ",".join(ESTIMATORS))
    ap.add_argument("--cache", default=None, help="folder for the training-view triangulation (default: a temp dir)")
    ap.add_argument("--fill", action="store_true",
                    help="also score the invalid pixels filled from the valid ones (data.depth_prior_fill)")
    ap.add_argument("--name", default=None, help="result file name (default prior_accuracy_<scene>)")
    args = ap.parse_args(argv)
    chosen = args.estimator.split(",")
    unknown = [e for e in chosen if e not in ESTIMATORS]
    if unknown:
        raise SystemExit(f"--estimator: unknown {unknown}; choose from {sorted(ESTIMATORS)}")

    scene = load_scene(args.data, split="llff", n_train=args.n_train, downscale=args.downscale)
    ref, per_view = view_reference_points(scene)
    with tempfile.TemporaryDirectory(prefix="warpgs-prior-") as tmp:
        tri = triangulate_scene(scene, Path(args.cache or tmp) / "triangulation", progress=False)
    scene = scene.with_points(tri.points)
    print(f"{scene.root.name}: train {scene.train}, test {scene.test}; {len(tri.points)} points triangulated from "
          f"the training views; reference: {len(ref.xyz)} points of all views", file=sys.stderr)
    payload = {"scene": str(scene.root), "train": scene.train, "test": scene.test, "downscale": args.downscale,
               "size": [scene.cameras[0].width, scene.cameras[0].height], "train_points": len(tri.points),
               "reference_points": len(ref.xyz), "estimators": {}}
    table = []
    for name in chosen:
        estimator = ESTIMATORS[name]()
        start = time.perf_counter()
        estimates = estimator.estimate(scene, scene.train, sources=scene.train)
        seconds = time.perf_counter() - start
        rows = [score_view(scene, v, estimates[v], ref.xyz[per_view[v]], args.fill) for v in scene.train]
        keys = ("abs_rel", "delta_1_25", "point_coverage", "pixel_coverage", "abs_rel_weighted", "abs_rel_oracle_align")
        fill_keys = ("abs_rel_filled", "delta_1_25_filled", "n_filled", "pixel_filled") if args.fill else ()
        mean = {k: mean_of(rows, k) for k in keys + fill_keys}
        for frac in ("0.25", "0.5"):
            mean[f"abs_rel_top{frac}"] = mean_of([{"x": r["top"][frac]["abs_rel"]} for r in rows if r["top"]], "x")
        payload["estimators"][name] = {"settings": vars(estimator).copy() | {"device": str(estimator.device)},
                                       "seconds": round(seconds, 2), "mean": mean, "views": rows}
        for r in rows + [{"view": "mean", **mean}]:
            top = r.get("top") or {}
            table.append([name, r["view"], r["abs_rel"], r["delta_1_25"], r["point_coverage"], r["pixel_coverage"],
                          r["abs_rel_weighted"], top.get("0.5", {}).get("abs_rel", r.get("abs_rel_top0.5")),
                          top.get("0.25", {}).get("abs_rel", r.get("abs_rel_top0.25")), r["abs_rel_oracle_align"]])
        print(f"  {name}: {seconds:.1f} s", file=sys.stderr)
        if args.fill:
            for r in rows + [{"view": "mean", **mean}]:
                print(f"  {name} {r['view']}: filled {r['pixel_filled']:.1%} of the pixels; at the {r['n_filled']:.0f} "
                      f"reference points on them AbsRel {r['abs_rel_filled']:.4f}, delta<1.25 "
                      f"{r['delta_1_25_filled']:.3f}", file=sys.stderr)
    cols = ["estimator", "view", "AbsRel", "δ<1.25", "pt cov", "px cov", "AbsRel (conf-wt)", "AbsRel top50%",
            "AbsRel top25%", "AbsRel (oracle align)"]
    print("| " + " | ".join(cols) + " |\n|" + "---|" * len(cols))
    for r in table:
        print("| " + " | ".join(c if isinstance(c, str) else ("n/a" if c is None else f"{c:.3f}") for c in r) + " |")
    payload["table"] = table
    path = write_json(args.name or f"prior_accuracy_{scene.root.name}", payload)
    print(f"wrote {path}", file=sys.stderr)
    return payload


if __name__ == "__main__":
    main()
