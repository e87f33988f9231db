"""Accuracy of the depth priors a benchmarks/sparse.py wave made (issue 30), without making them again: each
scene's prior (<out>/priors/<protocol>_<scene>/, or <protocol>_n<N>_<scene>/ under --n-train N) scored at its
training views against the capture's all-view SfM points (reference_depth.npz from benchmarks/sparse_data.py, else
the capture's sparse/0, as the benchmark scores test views), as benchmarks/prior_accuracy.py scores a fresh one.

    python benchmarks/sparse_prior_accuracy.py --out out/sparse --scenes data/sparse/fern,data/sparse/horns
    python benchmarks/sparse_prior_accuracy.py --out /tmp/b12 --protocol m360_24 --n-train 12 --scenes data/bonsai800@2

Per scene (mean over its training views): AbsRel and delta<1.25 at the reference points on valid prior pixels, the
share of those points on valid pixels (point coverage), the share of valid pixels, the AbsRel weighted by the prior's
confidence c and by c^4 (what the Marr terms weigh by at confidence_power 1 and 4), the share of pixels at confidence
>= 0.5 (where model.prior_points lifts its points beyond 9 views), and the largest |scale - 1| of the views'
alignment to the training views' SfM points (a metric sweep needs ~1; the prior's format.json records it; views kept
unaligned, whose valid pixels met too few points, are counted beside it). A capture without a reference gets the last
three only. Writes benchmarks/results/sparse_prior_accuracy_<name>.json (or $OUT).
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import numpy as np

from common import write_json
from sparse_runs import PROTOCOLS, load, parse_scene, prior_folder, protocol_for
from sparse_worker import reference_depth

from warpgs.data.depth.coverage import pixel_shares
from warpgs.data.depth.evaluate import point_depth_metrics
from warpgs.data.formats.view_files import FORMAT_FILE

KEYS = ("abs_rel", "delta1", "point_coverage", "valid_pixels", "abs_rel_confidence_weighted",
        "abs_rel_confidence4_weighted", "confident_pixels", "scale_error")
HEADERS = ("AbsRel", "δ<1.25", "point coverage", "valid pixels", "AbsRel, c-weighted", "AbsRel, c⁴-weighted",
           "c ≥ 0.5 pixels", "max abs(scale − 1)")


def alignment_scales(folder: Path) -> dict:
    """{view name: the scale of its alignment to the SfM points} from the prior folder's format.json, if recorded."""
    f = folder / FORMAT_FILE
    views = json.loads(f.read_text()).get("views", {}) if f.is_file() else {}
    return {name: v["alignment"]["scale"] for name, v in views.items() if (v.get("alignment") or {}).get("scale")}


def score_view(inv, valid, conf, depth) -> dict:
    """The reference-point scores of one view's prior against its sparse reference depth map (0: no point)."""
    rows, cols = np.nonzero(depth)
    pix, z = np.stack([cols, rows], 1), depth[rows, cols]
    m = point_depth_metrics(inv, valid, pix, z, confidence=conf)
    m4 = point_depth_metrics(inv, valid, pix, z, confidence=None if conf is None else conf ** 4)
    return {"abs_rel": m["abs_rel"], "delta1": m["delta_1_25"], "point_coverage": m["point_coverage"],
            "n_points": int(len(z)), "abs_rel_confidence_weighted": m.get("abs_rel_weighted"),
            "abs_rel_confidence4_weighted": m4.get("abs_rel_weighted")}


def score_scene(out: Path, tag: str, protocol, spec) -> dict:
    folder = prior_folder(out, tag, spec)
    if not ((folder / "prior.json").is_file() or (folder / FORMAT_FILE).is_file()):
        raise SystemExit(f"{folder}: no prior (run benchmarks/sparse.py with this --out first)")
    scene = load(spec, protocol).with_depth_priors(folder)
    reference, source = reference_depth(spec, scene, scene.train)
    scales = alignment_scales(folder)
    views = {}
    for i in scene.train:
        name = scene.names[i]
        inv, valid = scene.inv_depth_prior_np(i)
        conf = scene.prior_confidence_np(i)
        valid_share, confident_share = pixel_shares(valid, conf)
        row = {"valid_pixels": valid_share, "confident_pixels": confident_share,
               "scale_error": abs(scales[name] - 1.0) if name in scales else None}
        views[name] = {**row, **(score_view(inv, valid, conf, reference[name]) if reference else {})}
    mean = {k: statistics.fmean(v[k] for v in views.values()) for k in KEYS
            if k != "scale_error" and all(v.get(k) is not None for v in views.values())}
    if scales:  # the worst aligned view, not the mean; a metric sweep that met too few points is kept unaligned
        mean["scale_error"] = max((v["scale_error"] for v in views.values() if v["scale_error"] is not None),
                                  default=None)
        mean["unaligned_views"] = sum(v["scale_error"] is None for v in views.values())
    return {"mean": mean, "views": views, "reference": source if reference else f"none ({source})"}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="the benchmark's --out folder (its priors/)")
    ap.add_argument("--scenes", required=True, help="comma-separated scene folders, as given to benchmarks/sparse.py")
    ap.add_argument("--protocol", choices=list(PROTOCOLS), default="llff3")
    ap.add_argument("--n-train", type=int, default=None, help="training views, as given to benchmarks/sparse.py")
    ap.add_argument("--name", default=None, help="default: the protocol (and _n<N>)")
    args = ap.parse_args(argv)
    protocol, tag = protocol_for(args.protocol, args.n_train)
    out = Path(args.out).resolve()
    scenes = {}
    for s in args.scenes.split(","):
        spec = parse_scene(s, protocol)
        scenes[spec.name] = score_scene(out, tag, protocol, spec)
    print("| scene | " + " | ".join(HEADERS) + " |")
    print("|---|" + "---|" * len(HEADERS))
    for name, r in scenes.items():
        cells = ["n/a" if r["mean"].get(k) is None else f"{r['mean'][k]:.3f}" for k in KEYS]
        if r["mean"].get("unaligned_views"):
            cells[-1] += f" ({r['mean']['unaligned_views']} view(s) unaligned)"
        print(f"| {name} | " + " | ".join(cells) + " |")
    payload = {"protocol": tag, "out": str(out), "scenes": scenes}
    print(f"wrote {write_json(f'sparse_prior_accuracy_{args.name or tag}', payload)}")
    return payload


if __name__ == "__main__":
    main()
