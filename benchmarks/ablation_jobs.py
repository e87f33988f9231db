"""Run an ablation's settings x seeds as side-by-side processes, then merge them into one table and one JSON.

A 504x378 few-view run leaves an H100 mostly idle (host-bound), so six or seven runs share one GPU at about 1.7x
the time of one run alone. Each (setting, seed) is one process of benchmarks/ablation.py; its JSON and log go to a
temporary folder, and benchmarks/ablation_merge.py pools them (so a device that returns few files returns one).

    python benchmarks/ablation_jobs.py --jobs 6 --name ablation_fern_cuda_1000_seeds012 --only baseline,full \\
        --seeds 0,1,2 -- --data data/fern --device cuda --threads 2

Everything after `--` goes to every ablation.py process unchanged (not --only, --seeds or --name)."""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import ablation
import ablation_merge
from job_pool import Job, run_jobs

HERE = Path(__file__).resolve().parent


def parse(argv):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--jobs", type=int, default=2, help="processes at once (default 2)")
    ap.add_argument("--name", required=True, help="result file name of the merged table")
    ap.add_argument("--only", default=None, help="comma-separated settings (default: all of ablation.py's)")
    ap.add_argument("--seeds", default="0", help="comma-separated seeds (default 0)")
    ap.add_argument("rest", nargs=argparse.REMAINDER, help="-- then ablation.py's other arguments")
    args = ap.parse_args(argv)
    rest = args.rest[1:] if args.rest[:1] == ["--"] else args.rest
    for flag in ("--only", "--seeds", "--name"):
        if flag in rest:
            raise SystemExit(f"{flag}: give it to ablation_jobs.py, before `--`, not to every process")
    if args.jobs < 1:
        raise SystemExit(f"--jobs: expected at least 1, got {args.jobs}")
    table = ablation.REAL_SETTINGS if "--data" in rest else ablation.SETTINGS
    known = [s[0] for s in table]
    keys = args.only.split(",") if args.only else known
    unknown = [k for k in keys if k not in known]
    if unknown:
        raise SystemExit(f"--only: {unknown} are not settings; choose from {known}")
    return args, rest, keys, [int(s) for s in args.seeds.split(",")]


def main(argv=None) -> dict:
    args, rest, keys, seeds = parse(argv)
    with tempfile.TemporaryDirectory(prefix="warpgs-ablation-jobs-") as tmp:
        jobs = [Job(f"part_{key}_s{seed}", [sys.executable, str(HERE / "ablation.py"), *rest, "--only", key,
                                            "--seeds", str(seed), "--name", f"part_{key}_s{seed}"])
                for key in keys for seed in seeds]
        done = run_jobs(jobs, args.jobs, Path(tmp), env=dict(os.environ, OUT=tmp), summary=_summary)
        payloads = [(j.name, json.loads((Path(tmp) / f"{j.name}.json").read_text())) for j in done]
    merged = ablation_merge.merge(payloads)
    merged["processes_at_once"] = args.jobs  # shared device: the runs' seconds are not one run's alone
    return ablation_merge.write_table(args.name, merged)


def _summary(job: Job, log: str) -> str:
    return next((ln.strip() for ln in log.splitlines() if " seed " in ln and "psnr" in ln), job.name)


if __name__ == "__main__":
    main()
