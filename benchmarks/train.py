"""Held-out PSNR against training time on the dense synthetic scene (the built-in orbit: 31 training and 5
held-out views), for the warpgs trainer — and, with --gsplat, for a plain loop over gsplat's `rasterization`
and `DefaultStrategy` given the same data, initial points, view order, steps, learning rates and losses.

    python benchmarks/train.py                                     # CPU, configs/default.yaml (1500 steps)
    python benchmarks/train.py --steps 3000 --eval-every 250
    python benchmarks/train.py --device cuda --gsplat --size 512x384 --steps 7000 --config gaussians

Times are training time only (render, loss, backward, optimizer, densification; evaluation excluded), taken
with the GPU synchronised at each evaluation point. Prints a table and writes
benchmarks/results/train_<device>[_gsplat].json with every evaluation point and the time each system needs to
reach a few PSNR levels (and the ratio).

The two loops and what differs between them: benchmarks/train_compare.py.
"""
from __future__ import annotations

import argparse
import sys

import torch

from common import ROOT, print_table, write_json

sys.path.insert(0, str(ROOT))

from train_compare import initial_model, run_gsplat, run_warpgs, time_to  # noqa: E402
from warpgs.cli.commands import resolve_config_source  # noqa: E402
from warpgs.config.loader import load_config  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="default", help="preset or YAML (default: configs/default.yaml)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", type=int, help="training steps (default: the config's)")
    ap.add_argument("--eval-every", type=int, default=250)
    ap.add_argument("--size", default="128x96", help="synthetic scene resolution WxH")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gsplat", action="store_true", help="also run the plain gsplat loop (CUDA only)")
    ap.add_argument("--out", default=None, help="output folder for the warpgs run (default: a temp folder)")
    ap.add_argument("overrides", nargs="*", help="extra key=value config overrides (both systems)")
    args = ap.parse_args(argv)
    if args.gsplat and not args.device.startswith("cuda"):
        raise SystemExit("--gsplat needs --device cuda (gsplat has no CPU rasterizer)")
    width, height = (int(v) for v in args.size.lower().split("x"))
    import tempfile

    out = args.out or tempfile.mkdtemp(prefix="warpgs-bench-train-")
    overrides = [f"train.device={args.device}", f"train.seed={args.seed}", f"eval.every={args.eval_every}",
                 "train.progress=false", "train.checkpoint_every=0", "eval.save_images=false", "eval.lpips=false",
                 f"data.width={width}", f"data.height={height}", f"output.dir={out}"]
    if args.steps:
        overrides.append(f"train.steps={args.steps}")
    cfg = load_config(resolve_config_source(args.config), overrides + list(args.overrides))
    if cfg.data.path is not None:
        raise SystemExit("this benchmark runs on the built-in synthetic scene (data.path must be null)")

    trainer, start, counts = initial_model(cfg)
    runs = [run_warpgs(trainer, counts, args.eval_every)]
    if args.gsplat:
        runs.append(run_gsplat(cfg, args.eval_every, trainer.scene, start))

    rows = [{"system": r["system"], "step": p["step"], "seconds": p["seconds"], "psnr": p["psnr"], "ssim": p["ssim"],
             "primitives": p["num_primitives"]} for r in runs for p in r["points"]]
    print(f"held-out PSNR vs training time: synthetic orbit {width}x{height}, {cfg.train.steps} steps, "
          f"budget {cfg.strategy.max_primitives}, device {args.device}")
    print_table(rows, ["system", "step", "seconds", "psnr", "ssim", "primitives"])
    finals = [r["final"]["psnr"] for r in runs]
    levels = sorted({round(v, 1) for v in (min(finals) - 3.0, min(finals) - 1.0, min(finals) - 0.25)})
    reach = {f"{lv:.1f}": {r["system"]: time_to(r["points"], lv) for r in runs} for lv in levels}
    print("\nseconds to reach held-out PSNR:")
    for lv, t in reach.items():
        cells = "  ".join(f"{k} {'-' if v is None else f'{v:.1f}'}" for k, v in t.items())
        ratio = ""
        if args.gsplat and all(v for v in t.values()):
            ratio = f"  (warpgs/gsplat = {t['warpgs'] / t['gsplat']:.2f})"
        print(f"  {lv} dB: {cells}{ratio}")
    payload = {"device": args.device, "size": [width, height], "steps": cfg.train.steps, "seed": args.seed,
               "config": cfg.to_dict(), "runs": runs, "time_to_psnr": reach,
               "torch_threads": torch.get_num_threads()}
    if args.device.startswith("cuda"):
        payload["gpu"] = torch.cuda.get_device_name()
    name = f"train_{torch.device(args.device).type}" + ("_gsplat" if args.gsplat else "")
    print(f"\nwrote {write_json(name, payload)}")
    return payload


if __name__ == "__main__":
    main()
