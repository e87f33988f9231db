"""warpgs against gsplat's loop on one real capture over several seeds, as side-by-side processes on one or more
GPUs, then the seeds pooled (benchmarks/real_capture_seeds.py).

Each (seed, system) is one `real_capture.py --only SYSTEM --seed S` process; the two systems of a seed run on the
same GPU, seeds go round-robin over `--gpus`, at most `--per-gpu` processes share one. Every process writes its
own JSON when it ends (to --out, default benchmarks/results or $OUT), so a run cut short keeps the finished seeds.
Step times of processes that share a GPU are not a comparison: time a solo pair for that.

    python benchmarks/real_capture_jobs.py data/beer --seeds 1,2,3 --gpus 0,1,2 --per-gpu 2 --name beer_30k \\
        -- --device cuda --gsplat --steps 7000,30000 --eval-every 1000
    python benchmarks/real_capture_jobs.py data/phone64 --seeds 1,2,3,4 --gpus 0,1,2,3 --per-gpu 3 --name p \\
        --variant clamp099 train.alpha_max=0.99 -- --device cuda --gsplat --downscale 2 --steps 7000,30000

Everything after `--` goes to every real_capture.py process unchanged (not --only, --seed or --tag).

`--detach` starts the whole wave in a process session of its own and returns at once, its output in
<out>/<name>_jobs.log and its pid in <out>/<name>_jobs.log.pid: a device command's leftover processes are ended
when it returns, so a wave longer than one command must be detached, then waited for by later commands
(`while kill -0 $(cat PIDFILE) 2>/dev/null; do sleep 10; done`).

`--variant NAME KEY=VALUE ...` (repeatable) adds, for every seed, a third process on the pair's GPU: warpgs with
those config overrides (e.g. `--variant clamp0999 train.alpha_max=0.999`), tagged NAME_VARIANT and pooled on its
own against the same gsplat runs (real_capture_seeds_NAME_VARIANT.json). A variant with `train.steps=auto` (issue 31's
default run) is pooled with `real_capture_seeds.py --against-best`: its final model against the best point of gsplat's
curve, and its training time over gsplat's whole run's."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import real_capture_seeds
from common import RESULTS, asks_auto_steps
from job_pool import Job, detach, gpu_slot, parse_seeds_gpus, run_jobs

HERE = Path(__file__).resolve().parent
SYSTEMS = ("warpgs", "gsplat")


def split_at_dashes(argv):
    """(this script's arguments, real_capture.py's arguments): the command line cut at `--`."""
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    return argv[:cut], argv[cut + 1:]


def parse(argv):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="then `--` and real_capture.py's arguments for every process")
    ap.add_argument("data", help="scene folder (as real_capture.py takes it)")
    ap.add_argument("--seeds", default="0", help="comma-separated seeds (default 0)")
    ap.add_argument("--gpus", default="", help="comma-separated CUDA device indices (default: leave "
                                               "CUDA_VISIBLE_DEVICES alone, one group)")
    ap.add_argument("--per-gpu", type=int, default=2, help="processes at once on one GPU (default 2: a seed's pair)")
    ap.add_argument("--name", required=True, help="result name: the pooled table, and the runs' tag")
    ap.add_argument("--out", default=None, help="folder for every run's JSON (default: $OUT or benchmarks/results)")
    ap.add_argument("--variant", nargs="+", action="append", default=[], metavar=("NAME", "KEY=VALUE"),
                    help="also run warpgs with these config overrides for every seed (repeatable)")
    ap.add_argument("--detach", action="store_true", help="start the wave in its own process session and return "
                                                          "(output in <out>/<name>_jobs.log)")
    own, rest = split_at_dashes(argv)
    args = ap.parse_args(own)
    for flag in ("--only", "--seed", "--tag"):
        if flag in rest:
            raise SystemExit(f"{flag}: real_capture_jobs.py sets it for each process; leave it out after `--`")
    if "--gsplat" not in rest:
        raise SystemExit("give --gsplat after `--`: the runs compare warpgs with gsplat's loop")
    seeds, gpus = parse_seeds_gpus(args.seeds, args.gpus, args.per_gpu)
    if args.detach and not args.out and os.environ.get("OUT"):
        raise SystemExit("--detach: give --out with a folder of your own: the wave outlives this command, and a "
                         "device empties $OUT before its next command, results included (copy them there at the end)")
    variants = {}
    for name, *overrides in args.variant:
        if not name.isalnum() or name in variants:
            raise SystemExit(f"--variant {name}: expected a new name of letters and digits (it ends file names)")
        if not overrides or any("=" not in o for o in overrides):
            raise SystemExit(f"--variant {name}: expected config overrides KEY=VALUE after the name, got {overrides}")
        variants[name] = overrides
    args.variant = variants
    return args, rest, seeds, gpus


def plan(data: str, seeds, gpus, rest, name: str, variants=None):
    """The processes: both systems of each seed (and warpgs once per variant), a seed's runs on one GPU, seeds
    round-robin over the GPUs."""
    jobs = []
    for i, seed in enumerate(seeds):
        group, env = gpu_slot(gpus, i)
        runs = [(system, system, [], name) for system in SYSTEMS]
        runs += [(f"warpgs_{v}", "warpgs", overrides, f"{name}_{v}") for v, overrides in (variants or {}).items()]
        for label, system, overrides, tag in runs:
            cmd = [sys.executable, str(HERE / "real_capture.py"), data, *rest, *overrides, "--only", system,
                   "--seed", str(seed), "--tag", tag]
            jobs.append(Job(f"{label}_s{seed}", cmd, group, env))
    return jobs


def main(argv=None) -> dict:
    args, rest, seeds, gpus = parse(argv)
    out = Path(args.out or os.environ.get("OUT") or RESULTS)
    out.mkdir(parents=True, exist_ok=True)
    if args.detach:
        return _detach(argv, out, args.name)
    jobs = plan(args.data, seeds, gpus, rest, args.name, args.variant)
    run_jobs(jobs, args.per_gpu, out / f"{args.name}_logs", env=dict(os.environ, OUT=str(out)), summary=_summary)
    os.environ["OUT"] = str(out)  # the pooled tables go beside the runs
    files = _results(out, args.name)
    gsplat_runs = [f for f in files if "_gsplat_only_" in Path(f).name]
    for variant, overrides in args.variant.items():  # each variant against the same gsplat runs
        # train.steps=auto ends where its rule says, not on the marks: its final model against gsplat's best point
        best = ["--against-best"] if asks_auto_steps(overrides) else []
        real_capture_seeds.main([f"real_capture_seeds_{args.name}_{variant}", *gsplat_runs,
                                 *_results(out, f"{args.name}_{variant}"), *best])
    return real_capture_seeds.main([f"real_capture_seeds_{args.name}", *files])


def _detach(argv, out: Path, name: str) -> dict:
    """This same command without --detach (and with --out fixed), started in a session of its own."""
    own, rest = split_at_dashes(argv)
    own = [a for a in own if a != "--detach"]
    cmd = [sys.executable, str(Path(__file__).resolve()), *own, "--out", str(out), "--", *rest]
    log = out / f"{name}_jobs.log"
    pid = detach(cmd, log)
    print(f"detached: pid {pid}, output in {log}, pid in {log}.pid")
    return {"detached": pid, "log": str(log)}


def _results(out: Path, tag: str) -> list:
    """The run files real_capture.py wrote under this tag (not a pooled table)."""
    return sorted(str(p) for p in out.glob(f"real_capture_*_{tag}.json")
                  if not p.name.startswith("real_capture_seeds_"))


def _summary(job: Job, log: str) -> str:
    """The run's last scored line (system | step | seconds | psnr | ...), else its name."""
    rows = [ln.strip() for ln in log.splitlines() if ln.startswith(SYSTEMS) and "|" in ln]
    return f"{job.name}: {rows[-1]}" if rows else job.name


if __name__ == "__main__":
    main()
