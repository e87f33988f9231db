"""Where a training step's time goes, on a real capture: the whole Trainer.train_step against its render
forward+backward alone, the same with the NaN guard off (in alternating blocks, so both time the same growing model),
and a torch.profiler table of the busiest ops.

    python benchmarks/profile_train_step.py data/fern --device cuda --warmup 2000 --steps 200 data.downscale=8

Warm-up steps grow the model to a realistic size first (densification runs as in training). Writes
benchmarks/results/profile_train_step_<name>_<device>[_<tag>].json.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

from common import ROOT, sync, write_json

sys.path.insert(0, str(ROOT))

from warpgs.cli.commands import resolve_config_source  # noqa: E402
from warpgs.config.loader import load_config  # noqa: E402
from warpgs.config.schema import ALIASES  # noqa: E402
from warpgs.train.trainer import Trainer  # noqa: E402


def capture_arguments(ap: argparse.ArgumentParser, steps: int, steps_help: str) -> None:
    """The arguments of a benchmark that warms a Trainer up on a capture: data, --config, --device, --warmup,
    --steps, --tag and the key=value overrides (step_trace.py shares them)."""
    ap.add_argument("data", help="scene folder")
    ap.add_argument("--config", default="gaussians")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--warmup", type=int, default=2000, help="training steps before measuring")
    ap.add_argument("--steps", type=int, default=steps, help=steps_help)
    ap.add_argument("--tag", default="", help="suffix of the result file name (runs of one capture stay apart)")
    ap.add_argument("overrides", nargs="*", help="key=value config overrides")


def warmed_trainer(args, out_dir: str, run_steps=None) -> Trainer:
    """A quiet Trainer on args.data after args.warmup steps (densification runs as in training). run_steps: the
    run's length to set (None: the config's and the overrides')."""
    cfg = load_config(resolve_config_source(args.config), [f"data.path={args.data}", f"train.device={args.device}",
                                                            "eval.every=0", *args.overrides])
    if run_steps is not None:
        cfg.train.steps = run_steps
    cfg.output.dir = out_dir
    trainer = Trainer(cfg, quiet=True)
    for _ in range(args.warmup):
        trainer.train_step()
    return trainer


def profiler_activities(device: str) -> list:
    """torch.profiler's activities for `device`: the CPU, and CUDA on a GPU."""
    activities = [torch.profiler.ProfilerActivity.CPU]
    if torch.device(device).type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    return activities


def time_steps(trainer: Trainer, steps: int, device: str, before_step=None) -> float:
    """Mean seconds per Trainer.train_step over `steps` steps; `before_step()`, when given, runs before each one
    (inside the timing: step_slack.py queues GPU work there)."""
    sync(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        if before_step is not None:
            before_step()
        trainer.train_step()
    sync(device)
    return (time.perf_counter() - t0) / steps


def time_guard_on_off(trainer: Trainer, steps: int, device: str, rounds: int) -> tuple[float, float]:
    """Mean seconds per step with the NaN guard on and off, in alternating blocks of steps // rounds: the model
    keeps densifying while it is timed, so timing one setting after the other would time two model sizes."""
    block = max(1, steps // rounds)
    on, off = [], []
    for _ in range(rounds):
        for flag, out in ((True, on), (False, off)):
            trainer.config.train.nan_guard = flag
            out.append(time_steps(trainer, block, device))
    trainer.config.train.nan_guard = True
    return sum(on) / len(on), sum(off) / len(off)


def time_render_only(trainer: Trainer, steps: int, device: str) -> float:
    """Mean seconds of a forward+backward of the training render on the step's views, with the losses'
    outputs, nothing else (no loss terms, optimizer or strategy)."""
    views = [trainer.view(i) for i in trainer.scene.train[:steps]]
    sync(device)
    t0 = time.perf_counter()
    for k in range(steps):
        out = trainer.render(views[k % len(views)], trainer.outputs)
        loss = sum(v.float().sum() for v in (out.rgb, out.alpha, out.depth) if v is not None)
        loss.backward()
        trainer.model.zero_grad(set_to_none=True)
    sync(device)
    return (time.perf_counter() - t0) / steps


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    capture_arguments(ap, 200, "steps per measurement")
    ap.add_argument("--rounds", type=int, default=3,
                    help="alternating blocks of steps with the NaN guard on and off (each steps // rounds long)")
    ap.add_argument("--top", type=int, default=25, help="rows of the profiler table")
    args = ap.parse_intermixed_args(argv)

    with tempfile.TemporaryDirectory() as tmp:
        # A run just longer than the measurement, unless the overrides give its length (densification ends at a
        # fraction of it: a forced 8000-step run stops densifying at 4000, before a 5000-step warm-up ends).
        given = any(ALIASES.get(key, key) == "train.steps" for key in (o.split("=", 1)[0] for o in args.overrides))
        trainer = warmed_trainer(args, tmp, run_steps=None if given else args.warmup + 10 * args.steps)
        n = trainer.model.num_primitives
        step_s, no_guard_s = time_guard_on_off(trainer, args.steps, args.device, args.rounds)
        render_s = time_render_only(trainer, args.steps, args.device)
        activities = profiler_activities(args.device)
        with torch.profiler.profile(activities=activities) as prof:
            time_steps(trainer, min(args.steps, 50), args.device)
    key = "self_cuda_time_total" if len(activities) > 1 else "self_cpu_time_total"
    table = prof.key_averages().table(sort_by=key, row_limit=args.top)
    print(table)
    result = {"data": args.data, "device": args.device, "primitives": n, "warmup": args.warmup,
              "steps": args.steps, "rounds": args.rounds, "ms_per_step": 1e3 * step_s, "ms_per_step_no_nan_guard": 1e3 * no_guard_s,
              "ms_render_fwd_bwd": 1e3 * render_s, "ms_rest_of_step": 1e3 * (step_s - render_s),
              "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
              "profile_sorted_by": key, "profile": table}
    print(f"{n} primitives: step {1e3 * step_s:.2f} ms (NaN guard off: {1e3 * no_guard_s:.2f} ms); render fwd+bwd "
          f"alone {1e3 * render_s:.2f} ms; the rest {1e3 * (step_s - render_s):.2f} ms")
    name = Path(args.data).name
    write_json(f"profile_train_step_{name}_{args.device}" + (f"_{args.tag}" if args.tag else ""), result)
    return result


if __name__ == "__main__":
    main()
