"""Accuracy of the depth priors a benchmarks/sparse.py wave made (issue 30), without making them again: each
scene's prior (<out>/priors/<protocol>_<scene>/) scored at its training views against the capture's all-view SfM
points in reference_depth.npz (benchmarks/sparse_data.py), as benchmarks/prior_accuracy.py scores a fresh one.

    python benchmarks/sparse_prior_accuracy.py --out out/sparse --scenes data/sparse/fern,data/sparse/horns

Per scene (mean over its training views): AbsRel and delta<1.25 at the reference points on valid prior pixels,
the share of those points on valid pixels (point coverage), the share of valid pixels, the confidence-weighted
AbsRel, and the share of pixels at confidence >= 0.5 (where model.prior_points lifts its initial points).
Writes benchmarks/results/sparse_prior_accuracy_<name>.json (or $OUT/...).
"""
from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import numpy as np

from common import write_json
from sparse_data import REFERENCE_FILE
from sparse_runs import PROTOCOLS, load, parse_scene, prior_folder

from warpgs.data.depth.evaluate import point_depth_metrics

KEYS = ("abs_rel", "delta1", "point_coverage", "valid_pixels", "abs_rel_confidence_weighted", "confident_pixels")


def score_scene(out: Path, protocol: str, spec) -> dict:
    folder = prior_folder(out, protocol, spec)
    if not (folder / "prior.json").is_file():
        raise SystemExit(f"{folder}: no prior (run benchmarks/sparse.py with this --out first)")
    reference = spec.path / REFERENCE_FILE
    if not reference.is_file():
        raise SystemExit(f"{reference}: missing (benchmarks/sparse_data.py llff ... writes it)")
    scene = load(spec, PROTOCOLS[protocol]).with_depth_priors(folder)
    views = {}
    with np.load(reference) as ref:
        for i in scene.train:
            name = scene.names[i]
            inv, valid = scene.inv_depth_prior_np(i)
            conf = scene.prior_confidence_np(i)
            col_row_z = ref[name]
            m = point_depth_metrics(inv, valid, col_row_z[:, :2], col_row_z[:, 2], confidence=conf)
            views[name] = {"abs_rel": m["abs_rel"], "delta1": m["delta_1_25"], "point_coverage": m["point_coverage"],
                           "valid_pixels": float(valid.mean()), "n_points": int(len(col_row_z)),
                           "abs_rel_confidence_weighted": m.get("abs_rel_weighted"),
                           "confident_pixels": None if conf is None else float((conf >= 0.5).mean())}
    mean = {k: statistics.fmean(v[k] for v in views.values()) for k in KEYS
            if all(v[k] is not None for v in views.values())}
    return {"mean": mean, "views": views}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="the benchmark's --out folder (its priors/)")
    ap.add_argument("--scenes", required=True, help="comma-separated scene folders, as given to benchmarks/sparse.py")
    ap.add_argument("--protocol", choices=list(PROTOCOLS), default="llff3")
    ap.add_argument("--name", default=None, help="default: <protocol>")
    args = ap.parse_args(argv)
    out = Path(args.out).resolve()
    scenes = {}
    for s in args.scenes.split(","):
        spec = parse_scene(s, PROTOCOLS[args.protocol])
        scenes[spec.name] = score_scene(out, args.protocol, spec)
    print("| scene | AbsRel | δ<1.25 | point coverage | valid pixels | AbsRel, conf.-weighted | conf. ≥ 0.5 pixels |")
    print("|---|---|---|---|---|---|---|")
    for name, r in scenes.items():
        print(f"| {name} | " + " | ".join(f"{r['mean'].get(k, float('nan')):.3f}" for k in KEYS) + " |")
    payload = {"protocol": args.protocol, "out": str(out), "scenes": scenes}
    print(f"wrote {write_json(f'sparse_prior_accuracy_{args.name or args.protocol}', payload)}")
    return payload


if __name__ == "__main__":
    main()
