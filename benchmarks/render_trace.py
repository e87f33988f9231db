"""Where a GPU render call's time goes, warpgs beside gsplat: per call, the wall time, the GPU's busy time (so the
rest is the GPU waiting on the host), the host reads, and each kernel's time, from a torch.profiler trace.

    python benchmarks/render_trace.py --sizes 100000,1000000 --resolution 1920x1080 [--no-gsplat] [--tag T]
    python benchmarks/render_trace.py --primitive surfels ...     # 2D surfels (gsplat: rasterization_2dgs)

The scene and the calls are benchmarks/raster.py's (the default `rasterize(...)` call, RGB + alpha + depth; gsplat's
rasterization with RGB+ED). Each profiled call ends with a synchronisation, so a call's window holds only its own
GPU work. "reads" counts the read-backs a call makes: the device-to-host copies on the GPU's side of the trace,
whether issued through the runtime (torch's, gsplat's) or the driver (Warp's); "syncs" the runtime's
synchronisations the profiler sees (a torch read-back's stream sync, the closing device sync; Warp's go through the
driver and are not seen). Device-to-device and host-to-device copies (camera staging) do not stall the host; every
copy is listed by direction in "copies_per_call". "typical_call_timeline" is one call's GPU work in order with the GPU's
wait before each piece (the call with the median total wait): where the GPU waits on the host;
"typical_call_host_before_gpu" what the host did in that call before its first GPU work (the outermost torch ops,
runtime and driver calls the profiler saw, by name, and the rest: Python, which it does not see).
Writes benchmarks/results/render_trace_<device>[_<tag>].json ($OUT when set).
"""
from __future__ import annotations

import argparse
import collections
import json
import tempfile
import time
from pathlib import Path

import torch

from common import print_table, standard_scenes_module, sync, time_call, write_json
from raster import gsplat_calls, warpgs_calls
from step_trace import GPU_CATEGORIES, READS, busy_time

SYNCS = tuple(name for name in READS if "Synchronize" in name)  # runtime calls that wait for the GPU


def call_windows(events) -> list:
    """[start, end) of each profiled call (the record_function ranges named 'call')."""
    return sorted((e["ts"], e["ts"] + e["dur"]) for e in events
                  if e.get("name") == "call" and e.get("cat") == "user_annotation")


def copy_direction(name: str) -> str:
    """DtoH, HtoD, DtoD, ... from a GPU memcpy event's name ("Memcpy DtoH (Device -> Pinned)")."""
    parts = name.split()
    return parts[1] if len(parts) > 1 and parts[0] == "Memcpy" else name


def kernel_name(name: str, width: int = 90) -> str:
    """A kernel's name, short enough for a table but long enough to tell CUB's sort passes from its scans (their
    names share a long namespace prefix, dropped here)."""
    if "cub::" in name:
        name = "cub::" + name.split("::", 2)[-1]
    return name[:width]


def idle_before(gpu_events, start: float, end: float) -> list:
    """One call's GPU timeline in order: (kernel name, idle us before it, its us), the idle time being the GPU's wait
    since the call began or since its previous work ended; the last entry ("(end)", idle, 0) is the wait after the
    GPU's last work until the call returned. Where a call's GPU waits shows which host work it waits on."""
    timeline, free = [], start
    for e in sorted(gpu_events, key=lambda e: e["ts"]):
        timeline.append((kernel_name(e["name"], 60), max(e["ts"] - free, 0.0), e["dur"]))
        free = max(free, e["ts"] + e["dur"])
    timeline.append(("(end)", max(end - free, 0.0), 0.0))
    return timeline


HOST_CATEGORIES = ("cpu_op", "cuda_runtime", "cuda_driver")  # host work the profiler sees (Python it does not)


def median_index(timelines: list) -> int:
    """The call whose total GPU wait is the median's (a typical call, not an average of calls whose kernels need
    not line up)."""
    waits = [sum(idle for _, idle, _ in t) for t in timelines]
    return sorted(range(len(waits)), key=waits.__getitem__)[len(waits) // 2]


def timeline_rows(timeline: list) -> list:
    """One call's timeline as [name, idle us, busy us] rows, rounded for the JSON."""
    return [[name, round(idle, 1), round(busy, 1)] for name, idle, busy in timeline]


def host_before_first_work(host_events, start: float, first: float) -> dict:
    """What the host did from a call's start until its GPU's first work began at `first`: the outermost host events
    the profiler saw there (torch ops, runtime and driver calls; nested ones are inside their parent's time), total
    us by name, and "(not seen: Python)" for the rest of the span."""
    spans = sorted((e["ts"], e["ts"] + e["dur"], e["name"]) for e in host_events
                   if start <= e["ts"] and e["ts"] + e["dur"] <= first)
    totals, covered_to, seen = collections.Counter(), start, 0.0
    for begin, end, name in spans:
        if begin < covered_to:  # inside an outer event already counted
            continue
        totals[name] += end - begin
        seen += end - begin
        covered_to = end
    totals["(not seen: Python)"] = max(first - start - seen, 0.0)
    return {name: round(us, 1) for name, us in totals.most_common()}


def per_call_breakdown(events, calls: int) -> dict:
    """GPU busy microseconds per call, host reads per call, and kernel time per call by kernel name."""
    windows = call_windows(events)

    def inside(e) -> bool:  # the profiler's own work before and after the calls is left out
        return any(start <= e["ts"] < end for start, end in windows)

    gpu = [e for e in events if e.get("cat") in GPU_CATEGORIES and inside(e)]
    host = [e for e in events if e.get("cat") in HOST_CATEGORIES and inside(e)]
    busy, timelines, firsts = [], [], []
    for start, end in windows:
        mine = [e for e in gpu if start <= e["ts"] < end]
        busy.append(busy_time(mine)[1])
        timelines.append(idle_before(mine, start, end))
        firsts.append(min((e["ts"] for e in mine), default=end))
    kernels = collections.defaultdict(float)
    launches = collections.Counter()
    for e in gpu:
        name = kernel_name(e["name"])
        kernels[name] += e["dur"]
        launches[name] += 1
    copies = collections.Counter(copy_direction(e["name"]) for e in gpu if e.get("cat") == "gpu_memcpy")
    syncs = collections.Counter(e["name"] for e in events if e.get("cat") in ("cuda_runtime", "cuda_driver")
                                and e.get("name") in SYNCS and inside(e))
    wall = [end - start for start, end in windows]
    typical = median_index(timelines) if windows else None
    return {"calls_seen": len(windows),
            "profiled_wall_us": sum(wall) / max(len(wall), 1),
            "gpu_busy_us": sum(busy) / max(len(busy), 1),
            "reads_per_call": copies.get("DtoH", 0) / calls,
            "syncs_per_call": {k: v / calls for k, v in syncs.items()},
            "copies_per_call": {k: v / calls for k, v in copies.items()},
            "kernels_us_per_call": {k: kernels[k] / calls for k in sorted(kernels, key=lambda k: -kernels[k])},
            "launches_per_call": {k: launches[k] / calls for k in launches},
            "typical_call_timeline": [] if typical is None else timeline_rows(timelines[typical]),
            "typical_call_host_before_gpu": {} if typical is None else host_before_first_work(
                host, windows[typical][0], firsts[typical])}


def trace_calls(fn, calls: int) -> dict:
    for _ in range(5):
        fn()
    sync("cuda")
    activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with torch.profiler.profile(activities=activities) as prof:
        for _ in range(calls):
            with torch.profiler.record_function("call"):
                fn()
                torch.cuda.synchronize()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "trace.json"
        prof.export_chrome_trace(str(path))
        events = [e for e in json.loads(path.read_text())["traceEvents"] if e.get("ph") == "X"]
    return per_call_breakdown(events, calls)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="100000,1000000")
    ap.add_argument("--resolution", default="1920x1080")
    ap.add_argument("--calls", type=int, default=20, help="profiled calls per (system, mode)")
    ap.add_argument("--no-gsplat", action="store_true")
    ap.add_argument("--primitive", choices=["gaussians", "surfels"], default="gaussians")
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    scenes = standard_scenes_module()
    width, height = (int(v) for v in args.resolution.split("x"))
    rows, detail = [], []
    for n in (int(v) for v in args.sizes.split(",")):
        means, quats, scales, opacities, colors, viewmat, K, W, H = scenes.random_scene(
            n, width=width, height=height, device="cuda")
        surfels = args.primitive == "surfels"
        if surfels:
            scales = scales[:, :2].contiguous()
        scene = (means, quats, scales, opacities, colors, viewmat, K)
        systems = {"warpgs": warpgs_calls(scene, W, H, surfels, None)}
        if not args.no_gsplat:
            systems["gsplat"] = gsplat_calls(scene, W, H, surfels)
        for system, (fwd, fwd_bwd) in systems.items():
            for mode, fn in (("fwd", fwd), ("fwd_bwd", fwd_bwd)):
                plain_ms = time_call(fn, "cuda", warmup=3, repeats=50)
                t0 = time.perf_counter()
                found = trace_calls(fn, args.calls)
                row = {"n": n, "system": system, "mode": mode, "plain_ms": plain_ms,
                       "profiled_wall_ms": found["profiled_wall_us"] / 1e3, "gpu_busy_ms": found["gpu_busy_us"] / 1e3,
                       "gpu_waits_ms": (found["profiled_wall_us"] - found["gpu_busy_us"]) / 1e3,
                       "reads": found["reads_per_call"], "syncs": sum(found["syncs_per_call"].values()),
                       "trace_s": time.perf_counter() - t0}
                rows.append(row)
                detail.append(dict(row, **found))
                print_table([row], list(row))
                top = list(found["kernels_us_per_call"].items())[:12]
                for name, us in top:
                    print(f"    {us:8.1f} us x{found['launches_per_call'][name]:.0f}  {name}")
                waits = sorted(found["typical_call_timeline"], key=lambda r: -r[1])[:6]
                print("    GPU waits of a typical call, us before:",
                      ", ".join(f"{name[:40]} {idle:.0f}" for name, idle, _ in waits))
                print("    host work before its first GPU work, us:",
                      ", ".join(f"{name[:40]} {us:.0f}" for name, us in
                                list(found["typical_call_host_before_gpu"].items())[:8]))
    print_table(rows, ["n", "system", "mode", "plain_ms", "profiled_wall_ms", "gpu_busy_ms", "gpu_waits_ms", "reads",
                       "syncs"])
    result = {"primitive": args.primitive, "resolution": args.resolution, "calls": args.calls,
              "gpu": torch.cuda.get_device_name(), "rows": detail}
    suffix = "" if args.primitive == "gaussians" else "_surfels"
    write_json("render_trace_cuda" + suffix + (f"_{args.tag}" if args.tag else ""), result)
    return result


if __name__ == "__main__":
    main()
