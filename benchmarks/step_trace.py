"""Where a GPU training step waits: the GPU's busy share of the step, every host read (stream syncs and
device-to-host copies) with the Python line that made it, the host's time in Warp's synchronisations (the render's
tile-pair count), and where the GPU sat idle waiting for the host (each idle gap put on the launch that ended it),
from a torch.profiler trace of a few steps.

    python benchmarks/step_trace.py data/bonsai800 --device cuda --warmup 3000 --steps 10 train.steps=30000

Warm-up steps grow the model first (densification runs as in training). Python stacks make the profiled steps
slower than real ones (the plain step time is measured first, without the profiler); the reads and their call
sites are what to look at. Writes benchmarks/results/step_trace_<capture>_<device>[_<tag>].json.
"""
from __future__ import annotations

import argparse
import collections
import json
import tempfile
from pathlib import Path

import torch

from common import sync, write_json
from profile_train_step import capture_arguments, profiler_activities, time_steps, warmed_trainer

READS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cudaMemcpyAsync", "cudaMemcpy")
# Warp's waits go through the driver API, which the profiler does not record; their Python frames it does.
WARP_WAITS = (": synchronize_stream", ": synchronize_event", ": synchronize_device", ": synchronize")
GPU_CATEGORIES = ("kernel", "gpu_memcpy", "gpu_memset")


def busy_time(events) -> tuple[float, float]:
    """(span, busy) in microseconds of the GPU activity among trace events: the union of their intervals."""
    spans = sorted((e["ts"], e["ts"] + e["dur"]) for e in events if e.get("cat") in GPU_CATEGORIES)
    if not spans:
        return 0.0, 0.0
    busy, start, end = 0.0, spans[0][0], spans[0][1]
    for s, t in spans[1:]:
        if s > end:
            busy += end - start
            start, end = s, t
        else:
            end = max(end, t)
    busy += end - start
    return spans[-1][1] - spans[0][0], busy


def call_site(event, frames_by_thread, depth: int = 3) -> str:
    """The innermost `depth` warpgs frames (python_function events of the same thread) around a runtime call."""
    t = event["ts"]
    around = [f for f in frames_by_thread.get(event.get("tid"), ()) if f["ts"] <= t <= f["ts"] + f["dur"]]
    names = [f["name"] for f in sorted(around, key=lambda f: f["ts"]) if f["name"].startswith("warpgs/")]
    return " < ".join(names[-depth:][::-1]) or "(outside warpgs)"


def host_reads(events, steps: int) -> list:
    """One row per (runtime call, call site): calls and host microseconds per step, most time first. A
    cudaMemcpyAsync is a read only when it waits (the profiler cannot tell the direction here, so every copy is
    listed; host-to-device copies of small tensors are followed by a stream sync in torch, listed too)."""
    frames = python_frames(events)
    calls, micros = collections.Counter(), collections.Counter()
    for e in events:
        if e.get("cat") in ("cuda_runtime", "cuda_driver") and e.get("name") in READS:
            key = (e["name"], call_site(e, frames))
            calls[key] += 1
            micros[key] += e["dur"]
    return [{"call": k[0], "site": k[1], "per_step": calls[k] / steps, "host_us_per_step": micros[k] / steps}
            for k in sorted(calls, key=lambda k: -micros[k])]


def python_frames(events) -> dict:
    """The python_function events by thread (what call_site searches)."""
    frames = collections.defaultdict(list)
    for e in events:
        if e.get("cat") == "python_function":
            frames[e.get("tid")].append(e)
    return frames


def gpu_waits(events, steps: int, min_gap_us: float = 2.0) -> list:
    """Where the GPU sat idle waiting for the host: each gap of at least min_gap_us between GPU activities is put
    on the call site of the launch that ended it (the runtime or driver call with the kernel's correlation id; for
    launches the profiler does not see, such as Warp's, the Python frames of the busiest thread just before the
    kernel started), since until that launch the host was busy elsewhere. One row per site: gaps and idle
    microseconds per step, most idle first."""
    gpu = sorted((e for e in events if e.get("cat") in GPU_CATEGORIES), key=lambda e: e["ts"])
    host = [e for e in events if e.get("cat") in ("cuda_runtime", "cuda_driver")]
    by_correlation = {e["args"]["correlation"]: e for e in host if "correlation" in e.get("args", {})}
    frames = python_frames(events)
    main_tid = max(frames, key=lambda t: len(frames[t])) if frames else None
    gaps, micros = collections.Counter(), collections.Counter()
    end = None
    for e in gpu:
        if end is not None and e["ts"] - end >= min_gap_us:
            launch = by_correlation.get(e.get("args", {}).get("correlation", -1))
            if launch is not None and launch["ts"] < end:  # queued before the gap: the GPU waited on something else
                site = "(launched before the gap: not a wait for the host)"
            else:
                site = call_site(launch if launch is not None else {"ts": e["ts"] - 1, "tid": main_tid}, frames)
            gaps[site] += 1
            micros[site] += e["ts"] - end
        end = e["ts"] + e["dur"] if end is None else max(end, e["ts"] + e["dur"])
    return [{"site": k, "gaps_per_step": gaps[k] / steps, "idle_us_per_step": micros[k] / steps}
            for k in sorted(gaps, key=lambda k: -micros[k])]


def warp_waits(events, steps: int) -> list:
    """Host time in Warp's synchronisation calls (their Python frames), by warpgs call site: the render's wait for
    its tile-pair count among them. One row per site: calls and microseconds per step, most time first."""
    frames = python_frames(events)
    calls, micros = collections.Counter(), collections.Counter()
    for e in events:
        if e.get("cat") == "python_function" and e["name"].endswith(WARP_WAITS):
            site = call_site(e, frames)
            calls[site] += 1
            micros[site] += e["dur"]
    return [{"site": k, "per_step": calls[k] / steps, "host_us_per_step": micros[k] / steps}
            for k in sorted(calls, key=lambda k: -micros[k])]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    capture_arguments(ap, 10, "profiled steps")
    args = ap.parse_intermixed_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = warmed_trainer(args, tmp)
        plain_ms = 1e3 * time_steps(trainer, max(args.steps, 50), args.device)
        with torch.profiler.profile(activities=profiler_activities(args.device), with_stack=True) as prof:
            for _ in range(args.steps):
                trainer.train_step()
            sync(args.device)
        trace = Path(tmp) / "trace.json"
        prof.export_chrome_trace(str(trace))
        events = [e for e in json.loads(trace.read_text())["traceEvents"] if e.get("ph") == "X"]
    span, busy = busy_time(events)
    reads = host_reads(events, args.steps)
    waits = gpu_waits(events, args.steps)
    syncs = warp_waits(events, args.steps)
    result = {"data": args.data, "device": args.device, "warmup": args.warmup, "steps": args.steps,
              "primitives": trainer.num_primitives, "ms_per_step_plain": plain_ms,
              "profiled_gpu_span_ms_per_step": span / 1e3 / args.steps,
              "profiled_gpu_busy_ms_per_step": busy / 1e3 / args.steps, "host_reads": reads, "warp_waits": syncs,
              "gpu_waits": waits,
              "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None}
    print(f"{trainer.num_primitives} primitives: {plain_ms:.2f} ms a step without the profiler; profiled, the GPU "
          f"was busy {result['profiled_gpu_busy_ms_per_step']:.2f} of {result['profiled_gpu_span_ms_per_step']:.2f} ms")
    for r in reads:
        print(f"  {r['per_step']:5.1f}/step {r['host_us_per_step']:8.0f} us  {r['call']:22s} {r['site']}")
    print("  the host waiting in Warp's synchronisations:")
    for w in syncs:
        print(f"  {w['per_step']:5.1f}/step {w['host_us_per_step']:8.0f} us  {w['site']}")
    print("  where the GPU waited for the host (idle gaps, by the launch that ended them):")
    for w in waits[:15]:
        print(f"  {w['gaps_per_step']:5.1f}/step {w['idle_us_per_step']:8.0f} us  {w['site']}")
    write_json(f"step_trace_{Path(args.data).name}_{args.device}" + (f"_{args.tag}" if args.tag else ""), result)
    return result


if __name__ == "__main__":
    main()
