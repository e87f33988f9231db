"""Per-call host cost of the render ops, measured on the CPU: a scene so small (a few Gaussians, a tiny image) that
kernel time is negligible, so a call's time is the Python and launch work a GPU render pays before and between its
kernels (at 100k Gaussians on an H100 that is most of a forward).

    python benchmarks/host_cost.py [--trees /work/main,.] [--rounds 5]

Each tree (a source checkout) is timed in its own subprocess, trees alternating round by round on the same CPU, so
two versions of the code are compared under the same load. Per tree, call and round: the best of `--repeats` loops
of `--calls` calls (us per call); the table gives the least and the median over rounds (the least is the
host cost with the least interference from other processes) and their ratio between two trees. Rows: forward
and forward+backward of `rasterize` and `rasterize_surfels`, with the default input checks, both with the CPU's own
checks (torch, one host sync) and with the in-pipeline checks GPUs run (`PIPELINE_CHECK_DEVICES` plus "cpu"), one
CPU thread (WARPGS_CPU_THREADS=1), once with the kernels running and once with them stubbed out (`stubbed_kernels`:
host work only). Parts of a CPU call are CPU-only (the CPU read-back, the thread hand-out) and a GPU call has its own
(graph key and launch, the sync), so the stubbed rows approximate, not equal, a GPU call's host cost.
Writes benchmarks/results/host_cost_cpu.json ($OUT when set; --name renames).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

CASES = [(kind, mode, checks) for checks in ("torch", "pipeline") for kind in ("gaussians", "surfels")
         for mode in ("forward", "forward+backward")]


@contextmanager
def stubbed_kernels(on: bool):
    """Within the block (when `on`), CPU kernel launches, sorts and scans return at once: what is left of a call is
    host work only (the buffers keep what the warm-up calls computed, so every call takes the same path, tile-pair
    count included). Warp's own Python for a sort or scan goes too: a little less than a GPU pays."""
    import warp as wp
    from warp._src import context

    saved = (context.invoke, context.invoke_cpu_blocks, wp.utils.radix_sort_pairs, wp.utils.array_scan)
    if on:
        context.invoke = context.invoke_cpu_blocks = _nothing
        wp.utils.radix_sort_pairs = wp.utils.array_scan = _nothing
    try:
        yield
    finally:
        context.invoke, context.invoke_cpu_blocks, wp.utils.radix_sort_pairs, wp.utils.array_scan = saved


def _nothing(*args, **kwargs):
    return None


def measure(n: int, size: int, calls: int, repeats: int, stub: bool) -> dict:
    """In this process: us per call for every case (best of `repeats` loops of `calls` calls)."""
    import time

    import torch

    from warpgs import rasterize, rasterize_surfels
    from warpgs.render import gaussians, validation

    policy = validation if hasattr(validation, "PIPELINE_CHECK_DEVICES") else gaussians  # older trees: in gaussians

    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 4.0])
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.1 + 0.1
    opacities = torch.rand(n, generator=g) * 0.8 + 0.1
    colors = torch.rand(n, 3, generator=g)
    viewmat = torch.eye(4)
    K = torch.tensor([[float(size), 0.0, size / 2], [0.0, float(size), size / 2], [0.0, 0.0, 1.0]])
    results = {}
    for kind, mode, checks in CASES:
        render = rasterize if kind == "gaussians" else rasterize_surfels
        s = scales if kind == "gaussians" else scales[:, :2].contiguous()
        leaves = [t.clone().requires_grad_(True) for t in (means, quats, s, opacities, colors)]

        def forward():
            with torch.no_grad():
                render(means, quats, s, opacities, colors, viewmat, K, size, size, outputs=("rgb", "alpha", "depth"))

        def forward_backward():
            out = render(*leaves, viewmat, K, size, size, outputs=("rgb", "alpha", "depth"))
            (out.rgb.sum() + out.depth.sum()).backward()

        fn = forward if mode == "forward" else forward_backward
        added = checks == "pipeline" and "cpu" not in policy.PIPELINE_CHECK_DEVICES
        if added:
            policy.PIPELINE_CHECK_DEVICES.add("cpu")
        try:
            for _ in range(30):
                fn()
            best = float("inf")
            with stubbed_kernels(stub):
                for _ in range(repeats):
                    t0 = time.perf_counter()
                    for _ in range(calls):
                        fn()
                    best = min(best, (time.perf_counter() - t0) / calls * 1e6)
        finally:
            if added:
                policy.PIPELINE_CHECK_DEVICES.discard("cpu")
        results[f"{kind} {mode}, {checks} checks{', kernels stubbed' if stub else ''}"] = best
    return results


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--trees", default=".", help="comma-separated source checkouts to compare (alternating)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--n", type=int, default=4, help="Gaussians in the scene")
    ap.add_argument("--size", type=int, default=16, help="image width and height")
    ap.add_argument("--calls", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--name", default="host_cost_cpu")
    ap.add_argument("--_child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args._child:
        results = {}
        for stub in (False, True):
            results.update(measure(args.n, args.size, args.calls, args.repeats, stub))
        print(json.dumps(results))
        return
    trees = [str(Path(t).resolve()) for t in args.trees.split(",")]
    per_tree = {t: [] for t in trees}
    print("us per call, min / median over rounds, per tree:", ", ".join(trees))
    env = dict(os.environ, WARPGS_CPU_THREADS="1")
    for r in range(args.rounds):
        for t in (trees if r % 2 == 0 else trees[::-1]):
            cmd = [sys.executable, __file__, "--_child", f"--n={args.n}", f"--size={args.size}",
                   f"--calls={args.calls}", f"--repeats={args.repeats}"]
            out = subprocess.run(cmd, env=dict(env, PYTHONPATH=t), cwd=t, capture_output=True, text=True, check=True)
            per_tree[t].append(json.loads(out.stdout.strip().splitlines()[-1]))
    rows = []
    for key in per_tree[trees[0]][0]:
        row = {"case": key}
        for t in trees:
            vals = [run[key] for run in per_tree[t]]
            row[t] = dict(median_us=statistics.median(vals), min_us=min(vals), max_us=max(vals), rounds=vals)
        if len(trees) == 2:
            row["ratio_min"] = row[trees[1]]["min_us"] / row[trees[0]]["min_us"]
            row["ratio_median"] = row[trees[1]]["median_us"] / row[trees[0]]["median_us"]
        rows.append(row)
        cells = "  ".join(f"{row[t]['min_us']:7.1f} / {row[t]['median_us']:7.1f}" for t in trees)
        ratio = f"  x{row['ratio_min']:.3f} / x{row['ratio_median']:.3f}" if len(trees) == 2 else ""
        print(f"{key:62s} {cells}{ratio}")
    import platform

    meta = dict(machine=platform.machine(), processor=platform.processor(), cpus=os.cpu_count(), trees=trees,
                n=args.n, size=args.size, calls=args.calls, repeats=args.repeats, rounds=args.rounds,
                note="us per call, best of repeats per round; median and min-max over rounds; WARPGS_CPU_THREADS=1")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from common import write_json

    print("wrote", write_json(args.name, dict(meta=meta, rows=rows)))


if __name__ == "__main__":
    main()
