"""The sparse-view benchmark (issue 30): scenes x seeds x settings under the field's few-view protocols, one process a
run (side by side on each GPU), a JSON a run, then per-scene tables (mean ± standard error over seeds), the mean
over scenes, and the per-term ablation beside the paper's Table 2.

    python benchmarks/sparse.py --protocol llff3 --scenes data/sparse/fern,data/sparse/horns --dry-run
    python benchmarks/sparse.py --protocol llff3 --scenes data/sparse/fern --settings main --steps 300  # CPU smoke
    python benchmarks/sparse.py --protocol llff3 --scenes data/sparse/fern,data/sparse/flower,data/sparse/leaves,\\
        data/sparse/orchids --seeds 0,1,2 --settings paper --device cuda --gpus 0,1,2,3 --per-gpu 6 \\
        --out /tmp/sparse --name llff3 --detach
    python benchmarks/sparse.py ... --table        # only the tables, from the run files there are
    python benchmarks/sparse.py ... --steps 10000 --table --at-step 1000   # a longer run's scores at an earlier step
    python benchmarks/sparse.py ... --steps 10000 --table --along          # and every scored step's, one table

Protocols (every 8th view, 0, 8, 16, ... in sorted name order, tests; n_train views spread evenly over the rest
train: warpgs.data.formats.splits.llff_split, FSGS's and DNGaussian's reader):
  llff3    3 training views at 1/8 resolution (images_8): the FSGS / DNGaussian LLFF protocol
  m360_24  24 training views (FSGS's Mip-NeRF 360 protocol; FSGS reads images_8, i.e. ~390x260 for bonsai)
  m360_3   3 training views of the same captures
  lf3x3    a light field (warpgs.data.formats.lightfield): its 3x3 sub-grid spread over the array trains, every
           other view tests (the paper's protocol); benchmarks/stanford_lightfield.py prepares Stanford's archive
--n-train N keeps a protocol's rule with another count (its run files are then named <protocol>_nN_...).
A scene is a folder (LLFF, COLMAP or a light field), optionally `PATH@N` for data.downscale N (default: 8 for llff3,
1 for the 360 protocols, 4 for lf3x3; bonsai800's 800x533 photos at @2 are FSGS's images_8 size).
benchmarks/sparse_data.py prepares copies.

Settings (benchmarks/ablation.py's REAL_SETTINGS: the presets sparse_llff_baseline and sparse_llff as shipped
(`baseline`, `preset`), the paper's objective (`full`) with one term or part removed (`wo_<term>`), or the preset
with one change: `unpool` (proximity-guided unpooling at any view count; the preset's is on beyond 4 views),
`wo_unpool` (none), `virtual` (virtual views with at most 3 training views), `wo_drop` (no primitive dropout),
`depth_patch` (patch-normalised depth)): any comma-separated keys, or the groups main (baseline, preset, full), terms
(w/o each Marr and Gestalt term), paper (baseline, terms and full: the rows of the paper's Table 2), all. The depth
prior of each scene and protocol is estimated once (from its training views, as data.depth_priors=estimate does) and
shared by every run that uses it. Trailing key=value overrides and --marr KEY=VALUE (a warpgs.losses.marr setting)
apply to every run; a setting keeps the values it sets itself (an override that every chosen setting sets is an
error), and runs that differ only by them need their own --out (link its priors/ to the first's).
Depth (order, AbsRel, coverage) is scored at the capture's all-view SfM points seen by each test view
(reference_depth.npz from sparse_data.py, else sparse/0); without either only the image metrics are given. LPIPS is
given when its weights are on disk.

Runs are 1000 steps on either device (the presets' train.steps=by_views at 3 views; pass --steps for more views:
8000 at 24); a shorter or longer run (--steps) is the same schedule cut or extended (the presets give their horizons
in absolute steps). On the CPU the primitive budget is 10k (prior points scaled with it) unless --budget says
otherwise. --at-step N tabulates the held-out image scores that runs made with eval.every=N (their history) had at
step N; depth is scored at the end of a run only, so those tables leave it out (at the runs' last step, N = --steps,
the tables are the final ones, depth included).
Run files: <out>/runs/<protocol>_<scene>_<setting>_s<seed>.json; a run whose file exists is skipped (so a cut wave
resumes), one made with other steps, budget or downscale is an error. The tables go to
benchmarks/results/sparse_<name>.json (or $OUT). On a device, $OUT is emptied between commands: give --out a folder of
your own and copy the table there at the end.
"""
# This file is the driver (arguments, dry run, waves of worker processes, the table file); sparse_runs.py holds the
# plan and the run files, sparse_worker.py the two worker processes, sparse_tables.py the statistics and tables.
from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path
from typing import Optional

import ablation
from common import ROOT, asks_auto_steps, write_json
from job_pool import Job, detach, gpu_slot, parse_seeds_gpus, run_jobs
from sparse_runs import (FULL_STEPS, PROTOCOLS, Run, SceneSpec, expand_settings, load, protocol_for,  # the plan
                         needs_prior, parse_scene, plan, prior_done, read_run, run_budget, run_done, run_steps)
from sparse_along import along_runs, print_along  # scores along the runs (--along)
from sparse_tables import PAPER_TABLE2, SETTINGS, print_tables, summarise  # statistics and tables
from sparse_worker import make_prior, reference_source, train_one  # the worker processes
from warpgs.data.errors import SceneError


# --- the run files' tables ------------------------------------------------------------------------------------------
def tables(args, runs: list[Run], argv=None) -> dict:
    results, missing = [], []
    for run in runs:
        recorded = read_run(args, run)
        if recorded is not None:  # how to make the run again (one worker process)
            recorded.setdefault("command", shlex.join(worker_cmd(args, "run", run.scene, run)))
        if recorded is not None and args.at_step is not None:
            recorded = at_step(recorded, args.at_step)
        (results.append(recorded) if recorded is not None else missing.append(run.id))
    if not results:
        raise SystemExit(f"no run files under {Path(args.out) / 'runs'} for this plan")
    settings = [k for k in SETTINGS if k in {r.setting for r in runs}]
    summary = summarise(results, settings)
    first = results[0]
    scored = f" scored at step {args.at_step}" if args.at_step is not None else ""
    length = f"train.steps=auto within {run_steps(args)}" if asks_auto_steps(args.overrides) else first['steps']
    header = (f"\nsparse-view benchmark, protocol {args.protocol} ({args.proto.about}): "
              f"{len(results)} of {len(runs)} runs, {length} steps{scored}, {first['device']}, budget "
              f"{first['budget'] or 'preset'}" + (f"; missing {len(missing)}" if missing else ""))
    print_tables(summary, header)
    along = along_runs(results, settings)
    if args.along:
        print_along(along, {k: SETTINGS[k][0] for k in settings})
    payload = {"protocol": args.protocol, "tag": args.tag, "about": args.proto.about, "missing": missing,
               "command": shlex.join(["python", "benchmarks/sparse.py", *[a for a in (argv or sys.argv[1:])
                                                                           if a not in ("--table", "--detach")]]),
               "paper_table2": PAPER_TABLE2, "summary": summary, "along": along,
               "splits": {r["scene"]: {k: r[k] for k in ("size", "downscale", "train", "train_index", "test",
                                                         "test_index", "reference")} for r in results},
               "runs": results}
    print(f"\nwrote {write_json(f'sparse_{args.name}', payload)}", file=sys.stderr)
    return payload


def at_step(run: dict, step: int) -> dict:
    """The run's record with its image scores, size and time as its history has them at `step` (depth: None); at
    the run's last step, its final record (the periodic evaluation skips the last step: the final one scores it)."""
    if step == run.get("steps"):
        return run
    entry = next((h for h in run.get("history") or [] if h["step"] == step), None)
    if entry is None:
        raise SystemExit(f"--at-step {step}: run {run['id']} has no score at that step (history at "
                         f"{[h['step'] for h in run.get('history') or []]}; made with eval.every that divides it?)")
    return {**run, "psnr": entry["psnr"], "ssim": entry["ssim"], "lpips": entry.get("lpips"),
            "num_primitives": entry["num_primitives"], "train_seconds": entry["train_seconds"],
            "depth_order": None, "abs_rel": None, "coverage": None, "scored_at_step": step}


# --- the driver ----------------------------------------------------------------------------------------------------
def parse(argv):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--protocol", choices=list(PROTOCOLS), default="llff3")
    ap.add_argument("--scenes", required=True, help="comma-separated scene folders, each optionally PATH@DOWNSCALE")
    ap.add_argument("--n-train", type=int, default=None, help="training views, instead of the protocol's")
    ap.add_argument("--settings", default="main", help="setting keys and groups (main, terms, paper, all)")
    ap.add_argument("--seeds", default="0", help="comma-separated seeds (default 0)")
    ap.add_argument("--steps", type=int, default=None,
                    help=f"default {FULL_STEPS}: the presets' count at up to 9 training views "
                         "(train.steps=by_views; 24 views: 8000)")
    ap.add_argument("--budget", type=int, default=None,
                    help=f"strategy.max_primitives (default: the preset's on CUDA, {ablation.CPU_BUDGET} on CPU)")
    ap.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    ap.add_argument("--gpus", default="", help="comma-separated CUDA device indices, one group of processes each")
    ap.add_argument("--per-gpu", type=int, default=1, help="processes at once per GPU (or in all without --gpus)")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads per process (0: torch's default)")
    ap.add_argument("--pairs", type=int, default=2000, help="probe pairs per test view for the depth order")
    ap.add_argument("--out", default=str(ROOT / "out" / "sparse"), help="folder of the run files and priors")
    ap.add_argument("--name", default=None, help="table name: benchmarks/results/sparse_<name>.json "
                                                 "(default: <protocol>_<device>_<steps>)")
    ap.add_argument("--dry-run", action="store_true", help="list the runs (done / to do) and the splits, run nothing")
    ap.add_argument("--table", action="store_true", help="only the tables, from the run files there are")
    ap.add_argument("--at-step", type=int, default=None,
                    help="with --table: the image scores each run's history has at this step "
                         "(at --steps: the final scores)")
    ap.add_argument("--along", action="store_true",
                    help="with --table: also each setting's held-out PSNR at every step its runs were scored at")
    ap.add_argument("--detach", action="store_true", help="start the wave in its own process session and return")
    ap.add_argument("--keep-going", action="store_true",
                    help="a failed prior or run does not stop the others: the tables take the runs made, and the "
                         "command exits non-zero naming the failures")
    ap.add_argument("--marr", action="append", default=[], metavar="KEY=VALUE",
                    help="a warpgs.losses.marr setting for every run (e.g. confidence_power=2; repeatable); a "
                         "setting that sets the key itself (wo_confidence) keeps its own")
    ap.add_argument("--worker", choices=("prior", "run"), help=argparse.SUPPRESS)
    ap.add_argument("--setting", help=argparse.SUPPRESS)
    ap.add_argument("--seed", type=int, help=argparse.SUPPRESS)
    ap.add_argument("overrides", nargs="*", help="extra key=value config overrides for every run")
    args = ap.parse_args(argv)
    # The protocol's split rule, with another count under --n-train (e.g. FSGS-style 12 views); run files and priors
    # are named by the tag: the protocol, and the training-view count when it is not the protocol's.
    protocol, args.tag = protocol_for(args.protocol, args.n_train)
    args.proto = protocol
    scenes = [parse_scene(s, protocol) for s in args.scenes.split(",") if s]
    if len({s.name for s in scenes}) != len(scenes):
        raise SystemExit("--scenes: two scenes share a folder name (it names their run files)")
    seeds, gpus = parse_seeds_gpus(args.seeds, args.gpus, args.per_gpu)
    if args.gpus and not args.device.startswith("cuda"):
        raise SystemExit("--gpus: give --device cuda too")
    if args.at_step is not None and not args.table:
        raise SystemExit("--at-step: only with --table (it reads the histories of runs already made)")
    if args.along and not args.table:
        raise SystemExit("--along: only with --table (it reads the histories of runs already made)")
    if any("=" not in o for o in args.overrides):
        raise SystemExit(f"overrides: expected key=value, got {args.overrides}")
    args.marr_settings = parse_marr(args.marr)
    args.name = args.name or f"{args.tag}_{args.device.replace(':', '')}_{run_steps(args)}"
    return args, scenes, expand_settings(args.settings), seeds, gpus


def parse_marr(items: list[str]) -> dict:
    """--marr KEY=VALUE items -> {key: float}, checked as warpgs.losses.marr.configure checks them."""
    from warpgs.losses.marr import checked_settings

    settings = {}
    for item in items:
        key, _, value = item.partition("=")
        try:
            settings.update(checked_settings(**{key: value}))
        except ValueError as exc:
            raise SystemExit(f"--marr {item}: expected KEY=VALUE ({exc})") from None
    return settings


def worker_cmd(args, kind: str, scene: SceneSpec, run: Optional[Run] = None) -> list[str]:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", kind, "--protocol", args.protocol,
           "--scenes", f"{scene.path}@{scene.downscale}", "--device", args.device,
           "--out", str(Path(args.out).resolve()),
           "--pairs", str(args.pairs), "--threads", str(args.threads)]
    cmd += ["--n-train", str(args.n_train)] if args.n_train is not None else []
    cmd += [a for flag, v in (("--steps", args.steps), ("--budget", args.budget)) if v for a in (flag, str(v))]
    if run is not None:
        cmd += ["--setting", run.setting, "--seed", str(run.seed)]
    cmd += [a for key, value in args.marr_settings.items() for a in ("--marr", f"{key}={value:g}")]
    return cmd + list(args.overrides)


def dry_run(args, runs: list[Run], scenes: list[SceneSpec]) -> None:
    out = Path(args.out)
    for sc in scenes:
        prior = "done" if prior_done(out, args.tag, sc) else "to do"
        try:  # a dry run computes nothing: a folder of images alone is not reconstructed here
            loaded = load(sc, args.proto, run_sfm=False)
        except SceneError as e:
            print(f"{sc.name} ({sc.path}): {e}; the first run makes the poses with SfM; prior: {prior}")
            continue
        ref = reference_source(sc) or "none (image metrics only)"
        print(f"{sc.name} ({sc.path}, downscale {sc.downscale}, {loaded.cameras[0].width}x{loaded.cameras[0].height}"
              f", {len(loaded)} views): train {loaded.train} {[loaded.names[v] for v in loaded.train]}, test "
              f"{loaded.test}; depth reference: {ref}; prior: {prior}")
    done = [run_done(args, r) for r in runs]
    print(f"\n{len(runs)} runs ({sum(done)} done, {len(runs) - sum(done)} to do), {run_steps(args)} steps on "
          f"{args.device}, budget {run_budget(args) or 'preset'}, out {out}:")
    for r, d in zip(runs, done):
        print(f"  {'done ' if d else 'to do'}  {r.id}  ({SETTINGS[r.setting][1]})")


def main(argv=None):
    args, scenes, settings, seeds, gpus = parse(argv)
    if args.worker == "prior":
        return make_prior(args, scenes[0])
    if args.worker == "run":
        return train_one(args, Run(args.tag, scenes[0], args.setting, args.seed))
    runs = plan(args.tag, scenes, settings, seeds)
    ablation.warn_replaced_overrides({key: SETTINGS[key][2] for key in settings}, args.overrides)
    out = Path(args.out).resolve()
    args.out = str(out)
    if args.dry_run:
        return dry_run(args, runs, scenes)
    if args.table:
        return tables(args, runs, argv)
    if args.detach:
        if os.environ.get("OUT") and out.is_relative_to(Path(os.environ["OUT"]).resolve()):
            raise SystemExit("--detach: --out must not lie under $OUT, which a device empties before its next command")
        cmd = [sys.executable, str(Path(__file__).resolve()), *[a for a in (argv or sys.argv[1:]) if a != "--detach"]]
        pid = detach(cmd, out / f"{args.name}_jobs.log")
        print(f"detached: pid {pid}, output in {out / f'{args.name}_jobs.log'} (pid beside it)")
        return None
    failed, skipped = make_runs(args, runs, out, gpus)
    problems = ((f"{len(failed)} failed (logs in {out / 'logs'}): {', '.join(failed)}" if failed else "")
                + (f"; skipped, their prior failed: {', '.join(skipped)}" if skipped else ""))
    try:
        payload = tables(args, runs, argv)
    except SystemExit as no_runs:  # nothing made: the failures are the news
        raise SystemExit(f"{no_runs}\n{problems}" if problems else no_runs) from None
    if problems:
        raise SystemExit(problems)
    return payload


def make_runs(args, runs: list[Run], out: Path, gpus: list[int]) -> tuple[list[str], list[str]]:
    """Makes the runs not done yet, after the priors they need. Returns (failed jobs, runs skipped because their
    prior failed): both empty unless --keep-going, without which the first failure stops the wave."""
    todo = [r for r in runs if not run_done(args, r)]
    priors = [sc for sc in {r.scene: None for r in todo if needs_prior(r, args.overrides)}
              if not prior_done(out, args.tag, sc)]
    start = time.perf_counter()
    logs = out / "logs"
    failed, skipped = [], []
    if priors:
        print(f"priors: {', '.join(sc.name for sc in priors)}", file=sys.stderr, flush=True)
        jobs = [Job(f"prior_{args.tag}_{sc.name}", worker_cmd(args, "prior", sc), *gpu_slot(gpus, i))
                for i, sc in enumerate(priors)]
        made = {j.name for j in run_jobs(jobs, args.per_gpu, logs, keep_going=args.keep_going)}
        failed += [j.name for j in jobs if j.name not in made]
        no_prior = {sc.name for sc, j in zip(priors, jobs) if j.name not in made}
        skipped = [r.id for r in todo if r.scene.name in no_prior and needs_prior(r, args.overrides)]
        todo = [r for r in todo if r.id not in skipped]
    print(f"runs: {len(todo)} to do of {len(runs)}" + (f" ({len(skipped)} skipped: their prior failed)" if skipped
                                                        else ""), file=sys.stderr, flush=True)
    jobs = [Job(r.id, worker_cmd(args, "run", r.scene, r), *gpu_slot(gpus, i)) for i, r in enumerate(todo)]
    made = {j.name for j in run_jobs(jobs, args.per_gpu, logs, summary=lambda job, log: _summary(out, job),
                                     keep_going=args.keep_going)}
    failed += [j.name for j in jobs if j.name not in made]
    print(f"all runs done in {time.perf_counter() - start:.0f} s", file=sys.stderr)
    return failed, skipped


def _summary(out: Path, job: Job) -> str:
    f = out / "runs" / f"{job.name}.json"
    if not f.is_file():
        return job.name
    r = json.loads(f.read_text())
    return f"{job.name}: psnr {r['psnr']:.2f} ssim {r['ssim']:.4f} abs_rel {r['abs_rel']} ({r['wall_seconds']:.0f} s)"


if __name__ == "__main__":
    main()
