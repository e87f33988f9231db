"""Ablation of the sparse-view method (issue 6), after the paper's Table 2, on the synthetic 3x3 light field.

    python benchmarks/ablation.py                               # CPU, reduced run (500 steps, seed 0, budget 10k)
    python benchmarks/ablation.py --device cuda --steps 30000   # the full run
    python benchmarks/ablation.py --only baseline,full --seeds 0,1,2

Train: the 9 array views; test: the 4 held-out off-array views (between array positions). Every setting loads
its preset from configs/ (sparse_baseline, sparse_wo_*, sparse_lightfield), so the table measures exactly what
`warpgs-train <preset>` trains. Reported per setting, on the test views: PSNR, SSIM (LPIPS when its weights are on
disk), the relative-depth judgement (fraction of random pixel pairs, reference depths > 5% apart, whose rendered
order is right; empty pixels read as far), AbsRel of the rendered depth (alpha >= 0.5 pixels; coverage reported)
and the final number of primitives.

Runs shorter than 30k steps scale the 3DGS step schedule (densification window, SH bands, size pruning) by
steps/30000 with floors so a short run still densifies, and switch opacity resets off below 10k steps (the
depth-term decay always spans the whole run: it is relative to train.steps). The defaults used are printed and
stored in the JSON. Writes benchmarks/results/ablation_<device>_<steps>.json (or $OUT/...).
"""
from __future__ import annotations

import argparse
import math
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from common import ROOT, write_json

from warpgs.config.loader import load_config
from warpgs.metrics.depth import evaluate_depth
from warpgs.train.trainer import Trainer

# (label in the table, preset in configs/), in the paper's order.
SETTINGS = [
    ("baseline", "3DGS", "sparse_baseline"),
    ("wo_depth", "w/o depth", "sparse_wo_depth"),
    ("wo_depth_grad", "w/o depth_grad", "sparse_wo_depth_grad"),
    ("wo_depth_local", "w/o depth_local", "sparse_wo_depth_local"),
    ("wo_opacity", "w/o opacity", "sparse_wo_opacity"),
    ("wo_scale", "w/o scale", "sparse_wo_scale"),
    ("wo_count", "w/o count", "sparse_wo_count"),
    ("full", "Ours (full)", "sparse_lightfield"),
]
CPU_STEPS = 500
CPU_BUDGET = 10_000  # primitives, on CPU only (the presets' budget otherwise); the same for every setting


def schedule_overrides(steps: int) -> list[str]:
    """The 3DGS step schedule (for 30k steps) scaled to a shorter run."""
    if steps >= 30_000:
        return []
    f = steps / 30_000
    every = max(25, int(round(100 * f)))
    start = max(every, int(round(500 * f)))
    stop = max(start + every, steps // 2)
    return [f"strategy.refine_every={every}", f"strategy.refine_start={start}", f"strategy.refine_stop={stop}",
            f"strategy.reset_every={0 if steps < 10_000 else int(round(3000 * f))}",
            f"strategy.size_prune_start={max(start, int(round(3000 * f)))}",
            f"model.sh_interval={max(1, int(round(1000 * f)))}"]


def run_setting(preset: str, steps: int, seed: int, device: str, extra: list[str], workdir: Path,
                pairs: int) -> dict:
    overrides = [f"train.steps={steps}", f"train.seed={seed}", f"strategy.seed={seed}", f"train.device={device}",
                 "train.progress=false", "train.checkpoint_every=0", "eval.every=0", "eval.save_images=false",
                 f"output.dir={workdir / f'{preset}_s{seed}'}"] + schedule_overrides(steps) + extra
    cfg = load_config(ROOT / "configs" / f"{preset}.yaml", overrides)
    start = time.perf_counter()
    trainer = Trainer(cfg, quiet=True)
    result = trainer.fit()
    split, views = trainer.eval_views("test")
    depth = evaluate_depth(lambda v: trainer.render(v, ("depth", "alpha")), views,
                           num_primitives=trainer.model.num_primitives, num_pairs=pairs, seed=seed)
    m = result.metrics
    return {"preset": preset, "seed": seed, "steps": result.steps, "split": split, "psnr": m["psnr"],
            "ssim": m["ssim"], "lpips": m["lpips"], "depth_order": depth["depth_order"], "abs_rel": depth["abs_rel"],
            "coverage": depth["coverage"], "num_pairs": depth["num_pairs"], "num_primitives": result.num_primitives,
            "train_seconds": round(result.train_seconds, 1), "wall_seconds": round(time.perf_counter() - start, 1),
            "losses": [t.name for t in trainer.terms], "outputs": list(trainer.outputs),
            "per_view": {k: {**v, **depth["per_view"].get(k, {})} for k, v in m["per_view"].items()}}


def summarise(runs: list[dict]) -> dict:
    keys = ("psnr", "ssim", "lpips", "depth_order", "abs_rel", "coverage", "num_primitives", "train_seconds")
    out = {}
    for k in keys:
        vals = [r[k] for r in runs if r[k] is not None and not (isinstance(r[k], float) and math.isnan(r[k]))]
        if not vals:
            out[k] = None
            continue
        out[k] = statistics.fmean(vals)
        if len(vals) > 1:
            out[k + "_std"] = statistics.stdev(vals)
    return out


def fmt(v, digits: int, std=None) -> str:
    if v is None:
        return "n/a"
    s = f"{v:.{digits}f}"
    return s if std is None else f"{s} ± {std:.{digits}f}"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu", help="cpu (default), cuda, cuda:N")
    ap.add_argument("--steps", type=int, default=None, help=f"training steps (default: {CPU_STEPS} on CPU, 30000 on CUDA)")
    ap.add_argument("--seeds", default="0", help="comma-separated seeds (default 0)")
    ap.add_argument("--only", default=None, help="comma-separated subset of: " + ",".join(s[0] for s in SETTINGS))
    ap.add_argument("--budget", type=int, default=None,
                    help=f"strategy.max_primitives for every setting (default: {CPU_BUDGET} on CPU, the presets' on CUDA)")
    ap.add_argument("--pairs", type=int, default=2000, help="probe pairs per test view for the depth judgement")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    ap.add_argument("--name", default=None, help="result file name (default ablation_<device>_<steps>)")
    ap.add_argument("overrides", nargs="*", help="extra key=value config overrides for every setting")
    args = ap.parse_args(argv)
    steps = args.steps or (30_000 if args.device.startswith("cuda") else CPU_STEPS)
    seeds = [int(s) for s in args.seeds.split(",")]
    budget = args.budget or (None if args.device.startswith("cuda") else CPU_BUDGET)
    extra = ([f"strategy.max_primitives={budget}"] if budget else []) + list(args.overrides)
    chosen = SETTINGS if not args.only else [s for s in SETTINGS if s[0] in args.only.split(",")]
    if not chosen:
        raise SystemExit(f"--only: none of {args.only!r} is a setting")
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"ablation: {len(chosen)} settings x seeds {seeds}, {steps} steps on {args.device}, budget {budget}; "
          f"schedule {schedule_overrides(steps) or '3DGS defaults'}", file=sys.stderr, flush=True)
    rows, payload = [], {"steps": steps, "seeds": seeds, "device": args.device,
                         "torch_threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
                         "schedule_overrides": schedule_overrides(steps), "extra_overrides": extra, "budget": budget,
                         "settings": {}}
    with tempfile.TemporaryDirectory(prefix="warpgs-ablation-") as tmp:
        for key, label, preset in chosen:
            runs = []
            for seed in seeds:
                r = run_setting(preset, steps, seed, args.device, extra, Path(tmp), args.pairs)
                runs.append(r)
                print(f"  {label:16s} seed {seed}: psnr {r['psnr']:.2f} ssim {r['ssim']:.4f} "
                      f"order {r['depth_order']:.3f} absrel {r['abs_rel']:.4f} n {r['num_primitives']} "
                      f"({r['wall_seconds']:.0f} s)", file=sys.stderr, flush=True)
            s = summarise(runs)
            payload["settings"][key] = {"label": label, "preset": preset, "mean": s, "runs": runs}
            sd = lambda k: s.get(k + "_std")  # noqa: E731
            rows.append({"Setting": label, "PSNR ↑": fmt(s["psnr"], 2, sd("psnr")),
                         "SSIM ↑": fmt(s["ssim"], 4, sd("ssim")), "LPIPS ↓": fmt(s["lpips"], 3, sd("lpips")),
                         "Depth order ↑": fmt(s["depth_order"], 3, sd("depth_order")),
                         "AbsRel ↓": fmt(s["abs_rel"], 4, sd("abs_rel")), "Coverage": fmt(s["coverage"], 3),
                         "#Primitives": fmt(s["num_primitives"], 0), "Train s": fmt(s["train_seconds"], 0)})
    columns = list(rows[0])
    if all(r["LPIPS ↓"] == "n/a" for r in rows):
        columns.remove("LPIPS ↓")
    print(f"\nSynthetic 3x3 light field 128x96: train 9 array views, test 4 off-array views; {steps} steps, "
          f"seed(s) {','.join(map(str, seeds))}, {args.device}, primitive budget {budget or 'preset'}\n")
    print("| " + " | ".join(columns) + " |")
    print("|" + "|".join("---" for _ in columns) + "|")
    for r in rows:
        print("| " + " | ".join(r[c] for c in columns) + " |")
    payload["table"] = rows
    name = args.name or f"ablation_{args.device.replace(':', '')}_{steps}"
    path = write_json(name, payload)
    print(f"\nwrote {path}", file=sys.stderr)
    return payload


if __name__ == "__main__":
    main()
