"""PPGS language-field ablation on the built-in synthetic orbit scene (the paper's Table 2 on our data).

    python benchmarks/language.py [--device cpu|cuda] [--width 64 --height 48] [--steps 300] [--seeds 0]

Variants (same scene, steps, learning rates; every one trains the latent with L_r):
    3dgs            3D Gaussians, L1 + L_r                                  (no bridge)
    surfels         2D surfels,   L1 + L_r                                  (no bridge)
    surfels+bridge  surfels,      L1 + L_r + 1e-3 (L_c + L_f)               (bridge, plain sum)
    ppgs            surfels,      joint: L_rec/s_rec^2 + log s_rec^2 + L_rf/s_rf^2 + log s_rf^2
Reports test PSNR, mIoU / mAP of text queries for every label on the test views, training time, and rendering
FPS of rgb + alpha + features (no grad, test views; best of --fps-repeats passes, since the 2 shared CPU cores
make medians drift with other load). Prints a table and writes JSON to benchmarks/results/.
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

VARIANTS = {
    "3dgs": {"kind": "gaussians", "losses": {"l1": 1.0, "lang_feature": 1.0}, "bridge": False, "joint": False},
    "surfels": {"kind": "surfels", "losses": {"l1": 1.0, "lang_feature": 1.0}, "bridge": False, "joint": False},
    "surfels+bridge": {"kind": "surfels", "losses": {"l1": 1.0, "lang_feature": 1.0, "bridge_color": 1e-3,
                                                     "bridge_feature": 1e-3}, "bridge": True, "joint": False},
    "ppgs": {"kind": "surfels", "losses": {"ppgs": 1.0}, "bridge": True, "joint": True},
}


def run_variant(name: str, spec: dict, args, scene_path: Path, seed: int, work: Path) -> dict:
    import warpgs.language  # noqa: F401
    from warpgs.language.query import LanguageField
    from warpgs.train.trainer import Trainer

    losses = {"l1": 0.0, "dssim": 0.0, **spec["losses"]}
    overrides = [f"steps={args.steps}", f"device={args.device}", f"seed={seed}", f"data.path={scene_path}",
                 f"model.kind={spec['kind']}", f"model.sh_degree={args.sh_degree}", "model.sh_interval=100",
                 "eval.every=0", "eval.lpips=false", "eval.save_images=false", "train.checkpoint_every=0",
                 "train.progress=false", f"strategy.max_primitives={args.budget}",
                 f"strategy.refine_start={args.refine_start}", f"strategy.refine_stop={args.refine_stop}",
                 "strategy.size_prune_start=100000",
                 f"extensions.language.bridge={str(spec['bridge']).lower()}",
                 f"extensions.language.joint={str(spec['joint']).lower()}",
                 f"extensions.language.latent_lr={args.latent_lr}",
                 f"extensions.language.bridge_start={args.bridge_start}",
                 f"extensions.language.alternate_period={args.alternate_period}",
                 f"extensions.language.ae_steps={args.ae_steps}"]
    overrides += [f"losses.{k}={v}" for k, v in losses.items()] + list(args.set)
    out_dir = work / f"{name}_s{seed}"
    trainer = Trainer(str(ROOT / "configs" / "language.yaml"), overrides=overrides, out_dir=out_dir, quiet=True)
    t0 = time.perf_counter()
    result = trainer.fit()
    wall = time.perf_counter() - t0
    lang = json.loads((out_dir / "language_metrics.json").read_text())
    # rendering speed with features (what a query renders), no autograd
    field = LanguageField.from_trainer(trainer)
    _, views = trainer.eval_views()
    with torch.no_grad():
        for v in views[:1]:
            field.render(v)
        times = []
        for _ in range(args.fps_repeats):
            for v in views:
                if args.device.startswith("cuda"):
                    torch.cuda.synchronize()
                t = time.perf_counter()
                field.render(v)
                if args.device.startswith("cuda"):
                    torch.cuda.synchronize()
                times.append(time.perf_counter() - t)
    return {"variant": name, "seed": seed, "psnr": result.metrics["psnr"], "ssim": result.metrics["ssim"],
            "miou": lang["miou"], "map": lang["map"], "per_label": lang["per_label"],
            "train_seconds": result.train_seconds, "fit_wall_seconds": wall,
            "render_fps": 1.0 / min(times), "render_ms_median": 1000 * statistics.median(times),
            "num_primitives": result.num_primitives,
            "terms": lang.get("terms", {})}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--height", type=int, default=48)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--seeds", default="0", help="comma-separated seeds")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--sh-degree", type=int, default=1)
    ap.add_argument("--budget", type=int, default=4000)
    ap.add_argument("--refine-start", type=int, default=100)
    ap.add_argument("--refine-stop", type=int, default=250)
    ap.add_argument("--latent-lr", type=float, default=0.01)
    ap.add_argument("--bridge-start", type=int, default=100)
    ap.add_argument("--alternate-period", type=int, default=50)
    ap.add_argument("--ae-steps", type=int, default=400)
    ap.add_argument("--fps-repeats", type=int, default=5)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="extra trainer overrides for every variant (e.g. extensions.language.reduction=mean)")
    ap.add_argument("--out", help="JSON path (default benchmarks/results/language_<device>.json)")
    args = ap.parse_args(argv)

    from warpgs.data import default_scene

    scene_path = default_scene("orbit", args.width, args.height)
    seeds = [int(s) for s in args.seeds.split(",")]
    names = [n.strip() for n in args.variants.split(",")]
    rows = []
    with tempfile.TemporaryDirectory(prefix="warpgs-lang-bench-") as tmp:
        for seed in seeds:
            for name in names:
                row = run_variant(name, VARIANTS[name], args, scene_path, seed, Path(tmp))
                rows.append(row)
                print(f"{name:<16} seed {seed}: psnr {row['psnr']:.2f} mIoU {row['miou']:.3f} mAP {row['map']:.3f} "
                      f"train {row['train_seconds']:.1f} s fps {row['render_fps']:.1f}", flush=True)
    summary = {}
    for name in names:
        rs = [r for r in rows if r["variant"] == name]
        summary[name] = {k: statistics.mean(r[k] for r in rs)
                         for k in ("psnr", "miou", "map", "train_seconds", "render_fps", "num_primitives")}
    header = f"{'variant':<16} {'PSNR':>7} {'mIoU':>6} {'mAP':>6} {'train s':>8} {'FPS':>7} {'prims':>6}"
    print("\n" + header + "\n" + "-" * len(header))
    for name, s in summary.items():
        print(f"{name:<16} {s['psnr']:7.2f} {s['miou']:6.3f} {s['map']:6.3f} {s['train_seconds']:8.1f} "
              f"{s['render_fps']:7.1f} {s['num_primitives']:6.0f}")
    out = Path(args.out) if args.out else ROOT / "benchmarks" / "results" / f"language_{args.device.split(':')[0]}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    payload = {"settings": vars(args), "scene": f"synthetic orbit {args.width}x{args.height}",
               "machine": {"platform": platform.platform(), "torch": torch.__version__,
                           "threads": torch.get_num_threads()},
               "summary": summary, "runs": rows}
    out.write_text(json.dumps(payload, indent=1))
    print(f"-> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
