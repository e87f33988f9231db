"""Data-parallel training throughput and time to a held-out PSNR, on 1 and N processes (torchrun), at >= 1 MP a view.

    python benchmarks/distributed.py --device cuda --nproc 1,2                 # 1280x800 built-in scene, 1 and 2 GPUs
    python benchmarks/distributed.py --device cuda --nproc 1,2,4,8 --views-per-rank 2 --target-psnr 28
    python benchmarks/distributed.py --device cuda --nproc 1,2 --data data/phone64   # a real capture (2 MP views)
    python benchmarks/distributed.py --tiny                                     # CPU smoke test (gloo, 64x48)
    python benchmarks/distributed.py --device cuda --nproc 2 --nodes 2         # 2 torchrun agents (multi-node)
    python benchmarks/distributed.py --device cuda --nproc 2 train.parallel=model  # model-parallel

Each run is `torchrun --standalone --nproc_per_node=N -m warpgs.cli train ...` (N=1 too, so every run starts the
same way; with --nodes K, K agents on this host with c10d rendezvous, each its own GPUs, as K machines would run
it) on the built-in synthetic orbit scene at --size, with a global batch of N x --views-per-rank views a step.
With --scale-steps (the default) the step schedule (steps, refine_*, sh_interval, eval.every) is divided by the
batch size, as gsplat's --steps_scaler: every run sees the same number of views, so the time to a PSNR compares
equal work. Reported per run, from rank 0's log.jsonl and metrics.json:

- views_per_s: training views rendered per second of training (steps x batch / train_seconds; evaluation and
  checkpoints excluded; on CUDA the loss read-back of every view synchronises the GPU, so the time is real);
- steady_views_per_s and steady_speedup (over 1 process): the same after the first evaluation, without each
  process's one-off start-up (about 2 s on an H100), which a long run amortises and a 3000-view run does not;
- time_to_target_s: training seconds until a periodic held-out evaluation first reached --target-psnr
  (null when none did), and the PSNR/time of every evaluation;
- final held-out PSNR, primitives, steps and the scaling efficiency views_per_s(N) / (N x views_per_s(1)).
- phases (--phases): per rank, milliseconds a step spent drawing views, rendering + back-propagating, in the
  all-reduce, the optimizer, densification and clearing gradients (train.profile_phases: the GPU is synchronised at
  each boundary, which costs a little throughput). A rank whose all-reduce is long waits for the others.
- stage_seconds: rank 0's wall time of the run's one-off stages (set-up before the first step, final outputs after
  the last; warpgs/train/stage_clock.py): where wall_seconds beyond train_seconds goes.
- peak_gpu_memory_gb: rank 0's peak of allocated GPU memory (CUDA runs). With train.parallel=model (pass it as
  an override) this is what partitioning the primitives saves per GPU.

Writes benchmarks/results/distributed_<device>[_<tag>].json ($OUT when set). The first run generates and caches the
scene at --size in the unreported warm-up run (its views are ray traced on up to 8 threads at once; one at a time,
the 1280x800 scene took more than 6 minutes on a 32-core GPU host).
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import ROOT, print_table, write_json


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def scaled(value: int, factor: int, minimum: int = 1) -> int:
    return max(minimum, int(round(value / factor)))


def steady_views_per_s(evals: list) -> float | None:
    """Views per training second after the first evaluation: the rate without the start-up each process pays
    once (Warp loading its cached kernels, CUDA and NCCL set-up, the first launches), which does not shrink with
    more processes and would hide the scaling of a long run. None with fewer than two evaluations."""
    if len(evals) < 2 or evals[-1]["train_seconds"] <= evals[0]["train_seconds"]:
        return None
    return (evals[-1]["views_seen"] - evals[0]["views_seen"]) / (evals[-1]["train_seconds"] - evals[0]["train_seconds"])


def run_one(nproc: int, args, out: Path) -> dict:
    batch = nproc * args.views_per_rank
    f = batch if args.scale_steps else 1
    width, height = (int(v) for v in args.size.lower().split("x"))
    if args.data:  # a real capture: its own images, the every-8th-view split
        data = {"data.path": str(Path(args.data).resolve()), "data.split": "llff"}
        if args.downscale:
            data["data.downscale"] = args.downscale
    else:
        data = {"data.path": "null", "data.synthetic": "orbit", "data.width": width, "data.height": height}
    overrides = {
        **data, "train.device": args.device, "train.batch_size": batch, "train.seed": args.seed,
        "train.steps": scaled(args.steps, f), "eval.every": scaled(args.eval_every, f),
        "model.sh_interval": scaled(args.sh_interval, f),
        "strategy.refine_start": scaled(args.refine_start, f), "strategy.refine_every": scaled(args.refine_every, f),
        "strategy.refine_stop": scaled(args.refine_stop, f), "strategy.max_primitives": args.max_primitives,
        "train.progress": "false", "train.checkpoint_every": 0, "train.log_every": scaled(args.eval_every, f),
        "eval.lpips": "false", "eval.save_images": "false",
    }
    if args.phases:
        overrides["train.profile_phases"] = "true"
    train = ["-m", "warpgs.cli", "train", args.config, "--out", str(out), "--quiet",
             *[f"{k}={v}" for k, v in overrides.items()], *args.overrides]
    env = dict(os.environ, NCCL_NVLS_ENABLE="0")  # NVLink multicast off (docs/distributed.md)
    nodes = args.nodes if nproc > 1 else 1
    t0 = time.perf_counter()
    if nodes == 1:
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}", *train]
        procs = [subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)]
    else:  # one torchrun agent per "node" on this host, as on several machines (docs/distributed.md)
        if nproc % nodes:
            raise SystemExit(f"--nodes {nodes}: {nproc} processes do not split evenly over the nodes")
        per, port = nproc // nodes, free_port()
        cmd = [sys.executable, "-m", "torch.distributed.run", f"--nnodes={nodes}", f"--nproc-per-node={per}",
               "--rdzv-backend=c10d", f"--rdzv-endpoint=127.0.0.1:{port}", f"--rdzv-id=bench-{port}",
               "--max-restarts=0", *train]
        procs = []
        for node in range(nodes):
            node_env = dict(env)
            if args.device.startswith("cuda"):  # each node its own GPUs, as separate machines have
                node_env["CUDA_VISIBLE_DEVICES"] = ",".join(str(node * per + i) for i in range(per))
            procs.append(subprocess.Popen(cmd, env=node_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                          text=True))
            time.sleep(0.5)  # the first agent hosts the rendezvous store
    outputs = [p.communicate() for p in procs]
    wall = time.perf_counter() - t0
    for p, (stdout, stderr) in zip(procs, outputs):
        if p.returncode != 0:
            sys.stderr.write(stdout[-4000:] + stderr[-4000:])
            raise SystemExit(f"the run on {nproc} process(es) failed (exit {p.returncode}): {' '.join(cmd)}")
    metrics = json.loads((out / "metrics.json").read_text())
    evals = [{"step": h["step"], "views_seen": h["step"] * batch, "psnr": h["psnr"],
              "train_seconds": h["train_seconds"]} for h in metrics["history"]]
    evals.append({"step": metrics["steps"], "views_seen": metrics["steps"] * batch, "psnr": metrics["psnr"],
                  "train_seconds": metrics["train_seconds"]})
    reached = next((e for e in evals if e["psnr"] >= args.target_psnr), None)
    return {"nproc": nproc, "nodes": nodes, "batch_size": batch, "steps": metrics["steps"], "views_seen": metrics["steps"] * batch,
            "train_seconds": metrics["train_seconds"], "wall_seconds": round(wall, 2),
            "views_per_s": metrics["steps"] * batch / max(metrics["train_seconds"], 1e-9),
            "steady_views_per_s": steady_views_per_s(evals),
            "final_psnr": metrics["psnr"], "num_primitives": metrics["num_primitives"],
            "peak_gpu_memory_gb": (metrics["peak_gpu_memory_bytes"] / 1e9 if "peak_gpu_memory_bytes" in metrics
                                   else None),
            "time_to_target_s": None if reached is None else reached["train_seconds"],
            "views_to_target": None if reached is None else reached["views_seen"], "evals": evals,
            "phases": metrics.get("phases"),
            "stage_seconds": metrics.get("stage_seconds")}  # rank 0's set-up and final outputs, stage by stage


def print_phases(runs: list) -> None:
    """Milliseconds a step per phase, one row per run and rank."""
    rows = []
    for r in runs:
        for rank, split in enumerate(r.get("phases") or []):
            if split:
                rows.append({"nproc": r["nproc"], "rank": rank, **split["ms_per_step"],
                             "sum": round(sum(split["ms_per_step"].values()), 3)})
    if rows:
        print_table(rows, list(dict.fromkeys(k for row in rows for k in row)))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--nproc", default="1,2", help="process counts to compare, e.g. 1,2,4 (one GPU each on CUDA)")
    ap.add_argument("--device", default="cuda", help="cuda (NCCL) or cpu (gloo)")
    ap.add_argument("--size", default="1280x800", help="built-in scene resolution WxH (1280x800 = 1.02 MP)")
    ap.add_argument("--data", help="a real capture (COLMAP / LLFF / transforms.json folder) instead of the built-in "
                                    "scene; its points or triangulated points are made once, in the warm-up run")
    ap.add_argument("--downscale", type=int, default=None, help="data.downscale for --data")
    ap.add_argument("--nodes", type=int, default=1,
                    help="runs of several processes as this many torchrun agents on this host (c10d rendezvous, "
                         "each with its own GPUs): the multi-node launch, tried on one machine")
    ap.add_argument("--views-per-rank", type=int, default=1, help="views each process renders a step")
    ap.add_argument("--steps", type=int, default=3000, help="steps at batch 1 (divided by the batch, see above)")
    ap.add_argument("--eval-every", type=int, default=250)
    ap.add_argument("--sh-interval", type=int, default=1000)
    ap.add_argument("--refine-start", type=int, default=500)
    ap.add_argument("--refine-every", type=int, default=100)
    ap.add_argument("--refine-stop", type=int, default=2500)
    ap.add_argument("--max-primitives", type=int, default=1_000_000)
    ap.add_argument("--target-psnr", type=float, default=25.0)
    ap.add_argument("--no-scale-steps", dest="scale_steps", action="store_false",
                    help="keep the schedule in steps for every batch size (more views seen with more processes)")
    ap.add_argument("--config", default="default", help="preset or YAML the overrides apply to")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tag", default="", help="suffix of the result file name")
    ap.add_argument("--out", help="folder for the runs (default: a temporary folder)")
    ap.add_argument("--warmup-steps", type=int, default=30,
                    help="steps of an unreported first run that fills the kernel and scene caches (0: none)")
    ap.add_argument("--phases", action="store_true",
                    help="time each phase of the step on every rank (train.profile_phases) and print the split")
    ap.add_argument("--tiny", action="store_true", help="CPU smoke test: 64x48, 40 steps, gloo")
    ap.add_argument("overrides", nargs="*", help="extra key=value overrides for every run")
    args = ap.parse_args(argv)
    if args.tiny:
        args.device, args.size, args.steps, args.eval_every = "cpu", "64x48", 40, 10
        args.sh_interval, args.refine_start, args.refine_every, args.refine_stop = 10, 10, 10, 30
        args.max_primitives, args.target_psnr, args.tag = 20000, 12.0, args.tag or "tiny"
    counts = [int(n) for n in args.nproc.split(",")]
    root = Path(args.out or tempfile.mkdtemp(prefix="warpgs-bench-dist-"))
    width, height = (int(v) for v in args.size.lower().split("x"))
    if width * height < 1_000_000 and not args.tiny and not args.data:
        print(f"note: {args.size} is {width * height / 1e6:.2f} MP, under the 1 MP this benchmark is meant for",
              file=sys.stderr)

    if args.warmup_steps > 0:
        # Warp compiles its kernels on first use and caches them on disk: without this run the first measured
        # process count would pay the compilation inside its training time.
        warm = argparse.Namespace(**{**vars(args), "steps": args.warmup_steps, "scale_steps": False,
                                     "eval_every": args.warmup_steps})
        run_one(1, warm, root / "warmup")
    runs = [run_one(n, args, root / f"n{n}") for n in counts]
    base = next((r for r in runs if r["nproc"] == 1), None)
    for r in runs:
        r["scaling_efficiency"] = (r["views_per_s"] / (r["nproc"] * base["views_per_s"])) if base else None
        steady = base and r["steady_views_per_s"] and base["steady_views_per_s"]
        r["steady_speedup"] = r["steady_views_per_s"] / base["steady_views_per_s"] if steady else None
    payload = {"device": args.device, "data": args.data, "downscale": args.downscale,
               "size": None if args.data else [width, height],
               "megapixels": None if args.data else width * height / 1e6,
               "views_per_rank": args.views_per_rank, "scale_steps": args.scale_steps,
               "target_psnr": args.target_psnr, "steps_at_batch_1": args.steps, "config": args.config,
               "overrides": args.overrides, "runs": runs, "command": " ".join(sys.argv)}
    if args.tiny:
        payload["note"] = ("CPU smoke test of the script (gloo, 64x48): the figures say nothing about scaling, "
                           "least of all on a small machine where the processes share cores")
    if args.device.startswith("cuda"):
        import torch

        payload["gpu"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    print_table(runs, ["nproc", "nodes", "batch_size", "steps", "views_per_s", "scaling_efficiency", "steady_views_per_s",
                       "steady_speedup", "final_psnr",
                       "time_to_target_s", "num_primitives", "peak_gpu_memory_gb"])
    if args.phases:
        print_phases(runs)
    name = f"distributed_{args.device.split(':')[0]}" + (f"_{args.tag}" if args.tag else "")
    print(f"wrote {write_json(name, payload)}")
    return payload


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main()
