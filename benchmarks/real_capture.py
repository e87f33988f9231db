"""Held-out PSNR / SSIM (LPIPS where its weights are local) against training time on a real capture, for the
warpgs trainer and — with --gsplat — the plain gsplat loop on the same data, initial points, view order, steps,
learning rates and losses (benchmarks/train_compare.py).

    python benchmarks/real_capture.py data/beer --device cuda --gsplat --steps 7000,30000
    python benchmarks/real_capture.py data/fern --downscale 8 --steps 300           # CPU smoke run

DIR is any scene warpgs-train reads (COLMAP, transforms.json, LLFF poses_bounds.npy); the held-out views are
the every-8th LLFF split. Each --steps value is an evaluation point of one run to the largest (with the override
train.steps=auto warpgs stops by its own rule within the preset's bound, schedule.max_steps, cut to the largest; the
gsplat loop runs to it). Prints a table and writes benchmarks/results/real_capture_<name>_<device>[_gsplat].json
(every evaluation point, time per step of each system and their ratio, the largest one-step drop in primitive count)
and a PNG plot next to it.
"""
from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import torch

from common import ROOT, print_table, run_host, write_json

sys.path.insert(0, str(ROOT))

from train_compare import initial_model, run_gsplat, run_warpgs, warpgs_as_gsplat  # noqa: E402
from warpgs.cli.commands import resolve_config_source  # noqa: E402
from warpgs.config.loader import load_config  # noqa: E402
from warpgs.data.pose_checks import scene_pose_jumps  # noqa: E402


def plot(runs: list, title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for r in runs:
        ax.plot([p["seconds"] for p in r["points"]], [p["psnr"] for p in r["points"]], "o-", label=r["system"])
    ax.set_xlabel("training seconds")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def evaluation_period(eval_every: int, marks: list) -> int:
    """The trainer and the gsplat loop evaluate on a period: the largest one that lands on every mark and divides
    --eval-every (with --steps 7000,30000 --eval-every 5000 the minimum, 5000, never scored the 7k mark)."""
    return math.gcd(int(eval_every), *(int(m) for m in marks))


def auto_bound(configured: int, overrides: list, marks: list) -> int:
    """schedule.max_steps of a train.steps=auto run: the config's bound (the preset's, so that the run is the default a
    user gets), cut to the largest mark; a bound the overrides name must not exceed that mark (the run is still scored
    at every mark it reaches)."""
    if not any(o.split("=", 1)[0].strip() == "schedule.max_steps" for o in overrides):
        return min(int(configured), marks[-1])
    if configured > marks[-1]:
        raise SystemExit(f"schedule.max_steps={configured}: the bound of train.steps=auto cannot exceed the largest "
                         f"--steps mark ({marks[-1]}); raise --steps")
    return configured


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", help="scene folder (COLMAP, transforms.json or LLFF)")
    ap.add_argument("--config", default="gaussians", help="preset or YAML (default: gaussians, the 3DGS recipe)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", default="7000", help="comma-separated evaluation steps; the run goes to the largest "
                                                    "(with train.steps=auto warpgs's bound is the config's "
                                                    "schedule.max_steps, cut to the largest)")
    ap.add_argument("--eval-every", type=int, default=1000,
                    help="evaluation period; the run scores every gcd(this, each --steps mark) steps, so every mark "
                         "is scored")
    ap.add_argument("--downscale", type=int, default=None, help="data.downscale (default: the config's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gsplat", action="store_true", help="also run the plain gsplat loop (CUDA only)")
    ap.add_argument("--only", choices=("warpgs", "gsplat"), default=None,
                    help="run one system (with --gsplat): a 30k-step pair does not fit one 10-minute GPU call")
    ap.add_argument("--gsplat-reset", choices=("auto", "off"), default="auto",
                    help="auto: the gsplat loop applies the opacity resets gsplat 1.5.3's DefaultStrategy skips "
                         "(see benchmarks/train_compare.py); off: the release as it is")
    ap.add_argument("--loop-raster", choices=("gsplat", "warpgs"), default="gsplat",
                    help="the gsplat loop's rasterizer: gsplat's, or warpgs's (train_compare.warpgs_as_gsplat: then "
                         "the loop and strategy are gsplat's and the renderer is ours, which tells a renderer "
                         "difference from a loop one)")
    ap.add_argument("--tag", default="", help="suffix of the result file name")
    ap.add_argument("--lpips", action="store_true", help="score LPIPS at the end (needs its weights locally)")
    ap.add_argument("--out", default=None, help="output folder for the warpgs run (default: a temp folder)")
    ap.add_argument("overrides", nargs="*", help="extra key=value config overrides (both systems)")
    args = ap.parse_intermixed_args(argv)
    data = Path(args.data)
    if not data.is_dir():
        raise SystemExit(f"data: {data} is not a folder")
    if args.only == "gsplat" and not args.gsplat:
        raise SystemExit("--only gsplat needs --gsplat")
    if args.gsplat and not args.device.startswith("cuda"):
        raise SystemExit("--gsplat needs --device cuda (gsplat has no CPU rasterizer)")
    try:
        marks = sorted({int(s) for s in args.steps.split(",")})
    except ValueError:
        raise SystemExit(f"--steps: expected comma-separated integers, got {args.steps!r}")
    if not marks or marks[0] < 1:
        raise SystemExit(f"--steps: expected positive step counts, got {args.steps!r}")
    eval_every = evaluation_period(args.eval_every, marks)
    if eval_every < min(args.eval_every, marks[0]) and eval_every < 100:
        raise SystemExit(f"--steps {args.steps} and --eval-every {args.eval_every}: the only evaluation period that "
                         f"lands on every mark is {eval_every} steps; pick marks that share a larger one")
    out = args.out or tempfile.mkdtemp(prefix="warpgs-bench-real-")
    overrides = [f"data.path={data.resolve()}", "data.split=llff", f"train.device={args.device}",
                 f"train.seed={args.seed}", f"train.steps={marks[-1]}", f"eval.every={eval_every}",
                 "train.progress=false", "train.checkpoint_every=0", "eval.save_images=false",
                 f"eval.lpips={str(bool(args.lpips)).lower()}", f"output.dir={out}"]
    if args.downscale:
        overrides.append(f"data.downscale={args.downscale}")
    cfg = load_config(resolve_config_source(args.config), overrides + list(args.overrides))
    gsplat_cfg = cfg
    if cfg.train.steps == "auto":  # (override train.steps=auto) warpgs stops by its own rule within the largest mark
        cfg.schedule.max_steps = auto_bound(cfg.schedule.max_steps, list(args.overrides), marks)
        gsplat_cfg = cfg.copy()
        gsplat_cfg.train.steps = marks[-1]  # the gsplat loop runs its fixed schedule to the largest mark

    trainer, start, counts = initial_model(cfg)
    scene = trainer.scene
    print(f"{data.name}: {scene.summary()}; init {trainer.model.num_primitives} primitives "
          f"from {trainer.init_source}", flush=True)
    runs = [] if args.only == "gsplat" else [run_warpgs(trainer, counts, eval_every)]
    if args.gsplat and args.only != "warpgs":
        if args.loop_raster == "warpgs":
            runs.append(run_gsplat(gsplat_cfg, eval_every, scene, start, args.gsplat_reset, rasterization=warpgs_as_gsplat,
                                   system="gsplat loop, warpgs raster, warpgs visibility"))
        else:
            runs.append(run_gsplat(gsplat_cfg, eval_every, scene, start, args.gsplat_reset))

    rows = [{"system": r["system"], "step": p["step"], "seconds": p["seconds"], "psnr": p["psnr"], "ssim": p["ssim"],
             "primitives": p["num_primitives"]} for r in runs for p in r["points"]
            if p["step"] in [0] + marks or p is r["points"][-1]]  # a train.steps=auto run ends off the marks
    print(f"held-out PSNR vs training time: {data.name}, {marks[-1]} steps, device {args.device}")
    print_table(rows, ["system", "step", "seconds", "psnr", "ssim", "primitives"])
    per_step = {r["system"]: r["final"]["train_seconds"] / r["final"].get("steps", marks[-1]) for r in runs}
    for r in runs:
        d = r["largest_drop"]
        print(f"{r['system']}: {1e3 * per_step[r['system']]:.2f} ms/step; largest one-step primitive drop "
              f"{100 * d['fraction_removed']:.1f}% (step {d['step']}: {d['before']} -> {d['after']})"
              + (f"; flagged by rule: {d['pruned_by']}" if d.get("pruned_by") else ""))
    payload = {"data": str(data), "scene": scene.summary(), "device": args.device, "steps": marks,
               "seed": args.seed, "config": cfg.to_dict(), "runs": runs, "ms_per_step": per_step,
               "init_source": str(trainer.init_source), "gsplat_reset": args.gsplat_reset if args.gsplat else None}
    payload["loop_raster"] = args.loop_raster
    # A video capture whose poses jump has views that contradict each other: its scores say less
    # (docs/real_captures.md, beer).
    payload["pose_jumps"] = scene_pose_jumps(scene)
    if payload["pose_jumps"]:
        print(f"note: the capture's poses jump {len(payload['pose_jumps'])} times between neighbouring frames "
              "(benchmarks/pose_continuity.py): its views contradict each other")
    for r in runs:
        if r.get("schedule"):
            print(f"{r['system']}: steps=auto ended at step {r['final']['steps']}: "
                  + "; ".join(f"{d['decision']} @ {d['step']} ({d['reason']})" for d in r["schedule"]["decisions"]))
    if len(per_step) == 2 and "gsplat" in per_step:
        payload["step_time_ratio"] = per_step["warpgs"] / per_step["gsplat"]
        print(f"time per step warpgs / gsplat = {payload['step_time_ratio']:.2f}")
    if args.device.startswith("cuda"):
        payload["gpu"] = torch.cuda.get_device_name()
    payload["host"] = run_host(args.device)  # real_capture_seeds.py pairs timings only from the same host and GPU
    name = f"real_capture_{data.resolve().name}_{torch.device(args.device).type}" + ("_gsplat" if args.gsplat else "")
    name += f"_{args.only}_only" if args.only else ""
    if args.loop_raster != "gsplat" and args.only != "warpgs":
        name += "_warpgs_raster"
    name += f"_{marks[-1]}" if marks[-1] != 7000 else ""
    name += f"_seed{args.seed}" if args.seed else ""
    name += f"_{args.tag}" if args.tag else ""
    path = write_json(name, payload)
    try:
        plot(runs, f"{data.name}: held-out PSNR vs time ({args.device})", path.with_suffix(".png"))
    except ImportError:
        print("matplotlib not installed: no plot (pip install -e '.[bench]')")
    print(f"\nwrote {path}")
    return payload


if __name__ == "__main__":
    main()
