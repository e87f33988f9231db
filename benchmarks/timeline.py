"""Where a render call's wall time goes on the GPU: kernel time against idle time, and which host stage the GPU
was waiting on, for warpgs's op and (with --gsplat) gsplat's, from one torch.profiler (CUPTI) trace.

    python benchmarks/timeline.py --device cuda --n 100000 --resolution 1920x1080 --tile 8 --gsplat
    python benchmarks/timeline.py ... --variants default,fast+bwd=block   # several renderer variants

Each system runs `--iters` forward+backward calls (benchmarks/raster.py's calls: loss = sum of rgb and depth), each
synchronised like `common.time_call`, under the profiler. Per call it reports: wall time, GPU busy time (the union
of kernels, copies and fills), idle time, the number of kernels and copies, and the time from the call's start to
its first GPU work. For warpgs, the fast pipeline's stage hook marks each stage's end on the host, and every idle
stretch of the GPU is charged to the host stage in which it ended (the stage whose launch the GPU was waiting
for). Then the kernels with the most GPU time.

The profiler adds host time to every launch, so absolute times run above benchmarks/raster.py's; compare the
systems within one run. Prints tables and writes benchmarks/results/timeline_<device>_<n>.json ($OUT when set),
plus the Chrome trace of the last three calls of each system with --trace.
"""
from __future__ import annotations

import argparse
import gzip
import json
import os
import tempfile
from collections import defaultdict
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile, record_function

from common import print_table, standard_scenes_module, sync, write_json
from raster import gsplat_calls, warpgs_calls
from variants import describe, variant
from warpgs.render import fast_pipeline

GPU_CATEGORIES = ("kernel", "gpu_memcpy", "gpu_memset")
HOST_API_CATEGORIES = ("cuda_runtime", "cuda_driver", "cpu_op")  # kept in the --trace file only
ITER_PREFIX, MARK_PREFIX = "iter:", "stage-end:"


def mark_stage(name: str) -> None:
    """The stage hook: an instant host range named after the stage that just ended (no synchronisation)."""
    with record_function(MARK_PREFIX + name):
        pass


def profile_calls(systems, iters: int, device: str):
    """Runs every system's forward+backward `iters` times inside one profiler; returns the trace's events."""
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for name, call, is_warpgs in systems:
            fast_pipeline.stage_hook = mark_stage if is_warpgs else None
            try:
                for _ in range(iters):
                    sync(device)
                    with record_function(ITER_PREFIX + name):
                        call()
                        sync(device)
            finally:
                fast_pipeline.stage_hook = None
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "trace.json"
        prof.export_chrome_trace(str(path))
        return json.loads(path.read_text())["traceEvents"]


def host_profile(systems, iters: int, device: str, top: int = 30) -> None:
    """cProfile over each warpgs system's calls: where the host's time goes, by function (own time)."""
    import cProfile
    import pstats

    for name, call, is_warpgs in systems:
        if not is_warpgs:
            continue
        prof = cProfile.Profile()
        prof.enable()
        for _ in range(iters):
            call()
            sync(device)
        prof.disable()
        print(f"\n{name}: host functions with the most own time over {iters} calls (cProfile inflates them)")
        pstats.Stats(prof).sort_stats("tottime").print_stats(top)


def union_length(intervals) -> float:
    total, end = 0.0, float("-inf")
    for a, b in sorted(intervals):
        if b <= end:
            continue
        total += b - max(a, end)
        end = b
    return total


def idle_gaps(intervals, start: float, stop: float):
    """The stretches of [start, stop] that no interval covers."""
    gaps, cursor = [], start
    for a, b in sorted(intervals):
        if a > cursor:
            gaps.append((cursor, min(a, stop)))
        cursor = max(cursor, b)
    if cursor < stop:
        gaps.append((cursor, stop))
    return [(a, b) for a, b in gaps if b > a]


def short_name(name: str) -> str:
    for cut in ("(", "<"):
        name = name.split(cut)[0]
    return name.replace("void ", "").strip()[:70]


def analyse(events, iters_kept: int = 3):
    """Per system: mean per-call figures, idle time per host stage, top kernels, and the last calls' events."""
    timed = [e for e in events if e.get("ph") == "X" and "dur" in e]
    host = [e for e in timed if e.get("cat") == "user_annotation"]  # not their GPU-side copies
    calls = sorted((e for e in host if e["name"].startswith(ITER_PREFIX)), key=lambda e: e["ts"])
    gpu = sorted((e for e in timed if e.get("cat") in GPU_CATEGORIES), key=lambda e: e["ts"])
    marks = sorted((e for e in host if e["name"].startswith(MARK_PREFIX)), key=lambda e: e["ts"])
    api = [e for e in timed if e.get("cat") in HOST_API_CATEGORIES]
    per_system = defaultdict(list)
    for call in calls:
        per_system[call["name"][len(ITER_PREFIX):]].append(call)
    results = {}
    for system, its in per_system.items():
        rows, idle_by_stage, kernel_time, kept = [], defaultdict(float), defaultdict(float), []
        for k, call in enumerate(its):
            t0, t1 = call["ts"], call["ts"] + call["dur"]
            work = [e for e in gpu if t0 <= e["ts"] < t1]
            spans = [(e["ts"], e["ts"] + e["dur"]) for e in work]
            busy = union_length(spans)
            stage_ends = [(m["ts"], m["name"][len(MARK_PREFIX):]) for m in marks if t0 <= m["ts"] < t1]
            for a, b in idle_gaps(spans, t0, t1):
                stage = next((name for ts, name in stage_ends if ts >= b), "after the last stage")
                idle_by_stage[stage] += (b - a) / len(its)
            for e in work:
                if e.get("cat") == "kernel":
                    kernel_time[short_name(e["name"])] += e["dur"] / len(its)
            rows.append(dict(wall_us=call["dur"], gpu_busy_us=busy, idle_us=call["dur"] - busy,
                             kernels=sum(e.get("cat") == "kernel" for e in work),
                             copies_fills=sum(e.get("cat") != "kernel" for e in work),
                             to_first_gpu_us=(spans[0][0] - t0) if spans else None))
            if k >= len(its) - iters_kept:
                kept += [call] + work + [e for e in marks + api if t0 <= e["ts"] < t1]
        # the first call of each system is dropped from the means (allocator and launch caches settle there)
        steady = rows[1:] if len(rows) > 1 else rows
        mean = {key: sum(r[key] for r in steady) / len(steady) for key in steady[0] if steady[0][key] is not None}
        top = sorted(kernel_time.items(), key=lambda kv: -kv[1])[:12]
        results[system] = dict(mean=mean, idle_by_stage=dict(idle_by_stage), top_kernels=top, kept=kept)
    return results


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--n", type=int, default=100000)
    ap.add_argument("--resolution", default="1920x1080")
    ap.add_argument("--tile", type=int, default=8)
    ap.add_argument("--primitive", choices=["gaussians", "surfels"], default="gaussians")
    ap.add_argument("--variants", default="default", help="comma-separated (benchmarks/variants.py)")
    ap.add_argument("--gsplat", action="store_true")
    ap.add_argument("--iters", type=int, default=10)
    ap.add_argument("--trace", action="store_true", help="also write the last three calls' Chrome trace (gzip)")
    ap.add_argument("--host-profile", action="store_true",
                    help="also run warpgs's calls under cProfile (no CUDA profiler) and print the host functions "
                         "with the most own time")
    ap.add_argument("--out-name", default=None)
    args = ap.parse_args()
    if not args.device.startswith("cuda"):
        raise SystemExit("--device: the timeline needs a CUDA device (it reads the GPU's kernel activity)")
    W, H = (int(v) for v in args.resolution.split("x"))
    scene = list(standard_scenes_module().random_scene(args.n, width=W, height=H, device=args.device)[:7])
    surfels = args.primitive == "surfels"
    if surfels:
        scene[2] = scene[2][:, :2].contiguous()

    systems = []
    for spec in args.variants.split(","):
        def call(spec=spec, fwd_bwd=warpgs_calls(scene, W, H, surfels, args.tile)[1]):
            with variant(spec):
                fwd_bwd()
        with variant(spec):
            name = describe()
        systems.append((name, call, True))
    if args.gsplat:
        systems.append(("gsplat", gsplat_calls(scene, W, H, surfels)[1], False))
    for _, call, _ in systems:  # compile, allocate, warm up
        for _ in range(5):
            call()
    sync(args.device)

    if args.host_profile:
        host_profile(systems, args.iters, args.device)
    results = analyse(profile_calls(systems, args.iters, args.device))
    rows = [dict(system=s, **{k: round(v, 1) for k, v in r["mean"].items()}) for s, r in results.items()]
    print(f"{args.primitive} n={args.n} {W}x{H} tile {args.tile}, {torch.cuda.get_device_name()}: mean per "
          f"forward+backward call over {args.iters - 1} profiled calls (us)")
    print_table(rows, ["system", "wall_us", "gpu_busy_us", "idle_us", "to_first_gpu_us", "kernels", "copies_fills"])
    for s, r in results.items():
        if r["idle_by_stage"]:
            print(f"\n{s}: GPU idle, charged to the host stage it waited on (us per call)")
            print_table([dict(stage=k, idle_us=round(v, 1)) for k, v in
                         sorted(r["idle_by_stage"].items(), key=lambda kv: -kv[1])], ["stage", "idle_us"])
        print(f"\n{s}: kernels with the most GPU time (us per call)")
        print_table([dict(kernel=k, us=round(v, 1)) for k, v in r["top_kernels"]], ["kernel", "us"])
    meta = dict(device=args.device, gpu=torch.cuda.get_device_name(), primitive=args.primitive, n=args.n,
                resolution=f"{W}x{H}", tile_size=args.tile, iters=args.iters, torch=torch.__version__)
    name = args.out_name or f"timeline_{args.device.split(':')[0]}_{args.primitive}_{args.n}"
    payload = dict(meta=meta, systems={s: {k: v for k, v in r.items() if k != "kept"} for s, r in results.items()})
    print(f"wrote {write_json(name, payload)}")
    if args.trace:
        folder = Path(os.environ.get("OUT") or Path(__file__).resolve().parent / "results")
        kept = [e for r in results.values() for e in r["kept"]]
        with gzip.open(folder / f"{name}_trace.json.gz", "wt") as f:
            json.dump({"traceEvents": kept}, f)


if __name__ == "__main__":
    main()
