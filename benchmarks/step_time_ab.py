"""Training-step time of two code versions of warpgs, side by side: each version in its own process, the processes
in alternating rounds (A, B, A, B, ...), each growing the model through the same warm-up on the same capture and
then timing blocks of steps. For a change to the training step that benchmarks inside one process cannot compare
(the step itself, not the render op, differs).

    git worktree add /tmp/before HEAD~1          # or: mkdir /tmp/before && git archive HEAD~1 warpgs kernels | tar x -C /tmp/before
    python benchmarks/step_time_ab.py data/bonsai800 --trees before=/tmp/before,after=. --device cuda \\
        --warmup 3000 --steps 200 --blocks 3 --rounds 2

A tree is a folder holding warpgs/ (and kernels/). Both versions read the same config file (`--config`, this
checkout's gaussians preset by default, with train.steps=30000 so the schedule densifies as in a full run) plus the
key=value overrides.
Writes benchmarks/results/step_time_ab_<capture>_<device>[_<tag>].json: every process's block times and model
sizes, each version's mean over its blocks and the ratio of each version's mean to the first one's.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import ROOT, run_host, write_json


def import_tree(tree: str) -> None:
    """Imports warpgs and its kernels from `tree` (a folder with warpgs/ and kernels/ side by side, the source
    layout). An editable install of another checkout maps `warpgs.kernels` to that checkout's kernels/ (a
    subpackage not found under warpgs/ is looked up there), so the tree's folder is added to the package's path
    first, and both are checked."""
    root = Path(tree).resolve()
    sys.path.insert(0, str(root))
    import warpgs

    if (root / "kernels").is_dir():
        warpgs.__path__.append(str(root))
    import warpgs.kernels

    for module in (warpgs, warpgs.kernels):
        if not Path(module.__file__).resolve().is_relative_to(root):
            raise SystemExit(f"--trees: {tree} did not provide {module.__name__} (imported {module.__file__})")


def worker(tree: str, data: str, device: str, config: str, warmup: int, steps: int, blocks: int, overrides) -> dict:
    """Runs in the child process: the version in `tree` first on sys.path."""
    import_tree(tree)
    import torch
    from warpgs.config.loader import load_config
    from warpgs.train.trainer import Trainer

    cfg = load_config(config, [f"data.path={data}", f"train.device={device}", "eval.every=0",
                                                      "train.steps=30000", "train.progress=false", *overrides])
    cfg.output.dir = tempfile.mkdtemp()
    trainer = Trainer(cfg, quiet=True)
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    for _ in range(warmup):
        trainer.train_step()
    out = {"primitives_start": trainer.num_primitives, "ms": []}
    for _ in range(blocks):
        sync()
        t0 = time.perf_counter()
        for _ in range(steps):
            trainer.train_step()
        sync()
        out["ms"].append(1e3 * (time.perf_counter() - t0) / steps)
    out["primitives_end"] = trainer.num_primitives
    return out


def parse_trees(text: str) -> dict:
    """{name: (path, [overrides])} from NAME=PATH[@key=value;key=value],...: the overrides apply to that version
    only (one tree twice with different settings compares the settings)."""
    trees = {}
    for item in text.split(","):
        name, sep, spec = item.partition("=")
        path, _, extra = spec.partition("@")
        if not sep or not name or not path:
            raise SystemExit(f"--trees: expected NAME=PATH[@key=value;...] pairs separated by commas, got {item!r}")
        if not (Path(path) / "warpgs").is_dir():
            raise SystemExit(f"--trees: {path} holds no warpgs/ folder")
        overrides = [o for o in extra.split(";") if o]
        bad = [o for o in overrides if "=" not in o]
        if bad:
            raise SystemExit(f"--trees: {name}'s overrides must be key=value, got {bad}")
        trees[name] = (path, overrides)
    if len(trees) < 2:
        raise SystemExit("--trees: give at least two versions")
    return trees


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", help="scene folder")
    ap.add_argument("--trees", required=True, help="NAME=PATH[@key=value;...],...: the versions (with overrides of their own), the first is the reference")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--config", default="gaussians")
    ap.add_argument("--warmup", type=int, default=3000, help="training steps before timing (the model grows)")
    ap.add_argument("--steps", type=int, default=200, help="steps per timed block")
    ap.add_argument("--blocks", type=int, default=3, help="timed blocks per process")
    ap.add_argument("--rounds", type=int, default=2, help="processes per version, alternating")
    ap.add_argument("--tag", default="")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("overrides", nargs="*", help="key=value config overrides for every version")
    args = ap.parse_intermixed_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker, args.data, args.device, args.config, args.warmup, args.steps,
                                args.blocks, args.overrides)))
        return {}
    trees = parse_trees(args.trees)
    sys.path.insert(0, str(ROOT))
    from warpgs.cli.commands import resolve_config_source

    config = str(resolve_config_source(args.config))  # one file for every version: this checkout's preset
    runs = []
    for r in range(args.rounds):
        for name, (tree, own) in trees.items():
            cmd = [sys.executable, __file__, args.data, "--trees", args.trees, "--device", args.device, "--config",
                   config, "--warmup", str(args.warmup), "--steps", str(args.steps), "--blocks",
                   str(args.blocks), "--worker", tree, *args.overrides, *own]
            done = subprocess.run(cmd, capture_output=True, text=True)
            if done.returncode != 0:
                raise SystemExit(f"{name} (round {r + 1}) failed:\n{done.stderr[-3000:]}")
            run = {"version": name, "tree": tree, "overrides": own, "round": r + 1, **json.loads(done.stdout.strip().splitlines()[-1])}
            print(f"{name} round {r + 1}: {statistics.mean(run['ms']):.2f} ms/step ({run['primitives_start']} -> "
                  f"{run['primitives_end']} primitives)", flush=True)
            runs.append(run)
    means = {n: statistics.mean(ms for run in runs if run["version"] == n for ms in run["ms"]) for n in trees}
    first = next(iter(trees))
    result = {"data": args.data, "device": args.device, "config": args.config, "warmup": args.warmup,
              "steps": args.steps, "blocks": args.blocks, "rounds": args.rounds, "overrides": args.overrides,
              "host": run_host(args.device), "runs": runs, "ms_per_step": means,
              "ratio_to_first": {n: means[n] / means[first] for n in trees}}
    for n in trees:
        print(f"{n}: {means[n]:.2f} ms/step, {result['ratio_to_first'][n]:.3f}x {first}")
    write_json(f"step_time_ab_{Path(args.data).name}_{args.device}" + (f"_{args.tag}" if args.tag else ""), result)
    return result


if __name__ == "__main__":
    main()
