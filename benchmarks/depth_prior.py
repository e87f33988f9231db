"""Built-in depth prior (plane-sweep stereo) on the synthetic 3x3 light field: accuracy against the exact depth
and run time.

    python benchmarks/depth_prior.py                          # 128x96, the default scene of warpgs-train
    python benchmarks/depth_prior.py --sizes 128x96,256x192 --planes auto,32,64 --threads 2

For every size the scene is generated afresh (generation time reported too). Grid views are estimated from the
other 8 grid views; the off-grid (test) views from the 8 nearest grid views, as a prior for a held-out view
would be. Metrics are AbsRel and delta<1.25 over (a) pixels the estimator marks valid ("confident") and (b) all
pixels that have exact depth (sky excluded), plus the coverage of (a) within (b), and the scale/shift that the
alignment to the SfM points finds for the grid views (1 and 0 mean the stereo is already metric).
Prints a table and writes benchmarks/results/depth_prior.json (or $OUT/depth_prior.json).
"""
from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time

import numpy as np
import torch

from common import print_table, write_json

from warpgs.data import PlaneSweepStereo, align_depth_to_points, depth_metrics, load_scene
from warpgs.data.formats.synthetic import RigSettings, write_synthetic_scene


def evaluate(scene, estimates: dict, views: list[int]) -> dict:
    rows = []
    for v in views:
        gt, gt_valid = scene.depth_np(v)
        has_gt = gt_valid & np.isfinite(gt)
        est = estimates[v]
        pred = 1.0 / np.maximum(est.inv_depth, 1e-9)
        conf = depth_metrics(pred, gt, est.valid & has_gt)
        every = depth_metrics(pred, gt, has_gt)
        rows.append([conf["abs_rel"], conf["delta_1_25"], (est.valid & has_gt).sum() / has_gt.sum(),
                     every["abs_rel"], every["delta_1_25"]])
    mean = np.mean(rows, axis=0)
    return {"abs_rel": mean[0], "delta_1_25": mean[1], "coverage": mean[2], "abs_rel_all": mean[3],
            "delta_1_25_all": mean[4], "per_view_abs_rel": [r[0] for r in rows]}


def run(width: int, height: int, planes, workdir: str, threads: int) -> dict:
    folder = os.path.join(workdir, f"lf_{width}x{height}")
    if not os.path.isdir(folder):
        start = time.perf_counter()
        write_synthetic_scene(folder, "lightfield", RigSettings(width=width, height=height))
        generation = time.perf_counter() - start
    else:
        generation = None
    scene = load_scene(folder)
    estimator = PlaneSweepStereo(num_planes=None if planes == "auto" else int(planes), num_threads=threads)
    centre = scene.train[len(scene.train) // 2]
    if planes == "auto":  # report what the automatic choice was for the centre view
        near, far = estimator.depth_range(scene, centre)
        sources = [scene.cameras[s] for s in estimator.neighbours(scene, centre, scene.train)]
        planes = f"auto ({estimator.planes_for(scene.cameras[centre], sources, near, far)})"
    for v in scene.train + scene.test:
        scene.image_np(v)  # decode images up front: time the estimator, not PNG decoding
    start = time.perf_counter()
    grid = estimator.estimate(scene, scene.train)
    grid_seconds = time.perf_counter() - start
    start = time.perf_counter()
    held_out = estimator.estimate(scene, scene.test, sources=scene.train)
    test_seconds = time.perf_counter() - start
    fits = [align_depth_to_points(grid[v].inv_depth, grid[v].valid, scene.cameras[v],
                                  scene.points.xyz[scene.visible_points(v)]) for v in scene.train]
    return {"size": f"{width}x{height}", "planes": planes, "generation_s": generation,
            "s_per_view": grid_seconds / len(scene.train), "grid": evaluate(scene, grid, scene.train),
            "held_out": evaluate(scene, held_out, scene.test), "held_out_s_per_view": test_seconds / len(scene.test),
            "alignment_scale": float(np.mean([f.scale for f in fits])),
            "alignment_shift": float(np.mean([f.shift for f in fits])),
            "alignment_median_relative": float(np.mean([f.median_relative for f in fits]))}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="128x96", help="comma-separated WxH list")
    parser.add_argument("--planes", default="auto", help="comma-separated plane counts, or auto")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads for the sweep (estimator default 1)")
    args = parser.parse_args()
    results = []
    with tempfile.TemporaryDirectory(prefix="warpgs-depth-bench-") as workdir:
        for size in args.sizes.split(","):
            w, h = (int(x) for x in size.lower().split("x"))
            for planes in args.planes.split(","):
                results.append(run(w, h, planes, workdir, args.threads))
    rows = [{"size": r["size"], "planes": r["planes"], "views": part,
             "AbsRel": r[part]["abs_rel"], "d<1.25": r[part]["delta_1_25"], "coverage": r[part]["coverage"],
             "AbsRel(all)": r[part]["abs_rel_all"], "d<1.25(all)": r[part]["delta_1_25_all"],
             "s/view": r["s_per_view"] if part == "grid" else r["held_out_s_per_view"]}
            for r in results for part in ("grid", "held_out")]
    print_table(rows, ["size", "planes", "views", "AbsRel", "d<1.25", "coverage", "AbsRel(all)", "d<1.25(all)",
                       "s/view"])
    for r in results:
        print(f"{r['size']} / planes {r['planes']}: alignment to SfM points scale {r['alignment_scale']:.4f}, "
              f"shift {r['alignment_shift']:.2e}; scene generation "
              + (f"{r['generation_s']:.2f} s" if r["generation_s"] is not None else "reused"))
    env = {"python": platform.python_version(), "torch": torch.__version__, "sweep_threads": args.threads,
           "cpus": os.cpu_count(), "machine": platform.machine(), "load_avg": os.getloadavg()}
    path = write_json("depth_prior", {"benchmark": "depth_prior", "estimator": "plane_sweep", "env": env,
                                      "results": results})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
