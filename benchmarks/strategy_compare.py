"""The warpgs Trainer against gsplat's training loop and DefaultStrategy, both rendering with warpgs's rasterizer:
what is left between them is the loop and the densification strategy, not the renderer. Runs on the CPU.

    python benchmarks/strategy_compare.py data/phone64 --downscale 8 --steps 4000 --gsplat-src /path/to/gsplat-1.5.3

The gsplat side is benchmarks/train_compare.py's plain loop (same data, initial points, learning rates, losses and
steps; gsplat's `DefaultStrategy`, with the opacity resets that gsplat 1.5.3 skips applied by the loop) with
`rasterization` replaced by a shim over `warpgs.rasterize`. Only gsplat's Python sources are needed
(`--gsplat-src` a source tree whose `gsplat/` holds them, or an installed gsplat): its strategy imports no CUDA
code. Why: on the phone capture warpgs trails gsplat's loop by 0.5–1.9 dB although both rasterizers give the same
gradients (benchmarks/grad_vs_gsplat.py); this tells a loop/strategy difference from a renderer one.
`--only warpgs|loop` runs one side (two processes on two cores finish sooner than one after the other).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import torch

from common import ROOT, capture_config, import_gsplat_python, print_table, write_json

sys.path.insert(0, str(ROOT))

from train_compare import initial_model, run_gsplat, run_warpgs  # noqa: E402
from warpgs.render.gaussians import rasterize  # noqa: E402


class _ScreenMeans:
    """What gsplat's strategy reads as info["means2d"]: .grad as [1, N, 2]; retain_grad() is a no-op because
    warpgs's means2d is a leaf that keeps its gradient anyway."""

    def __init__(self, leaf: torch.Tensor):
        self.leaf = leaf

    def retain_grad(self) -> None:
        pass

    @property
    def grad(self) -> torch.Tensor:
        return self.leaf.grad[None]


def warpgs_as_gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, sh_degree,
                     packed=False, backgrounds=None, near_plane=0.01, far_plane=1e10, visibility="warpgs"):
    """gsplat's `rasterization` signature (one camera, packed=False) over warpgs.rasterize. visibility: which
    primitives the strategy counts as seen (its radii > 0): "warpgs" (reaches a tile, `out.visible`) or "gsplat"
    (gsplat 1.5.3's opacity-aware box meets the image, benchmarks/visibility_compare.py)."""
    out = rasterize(means, quats, scales, opacities, colors, viewmats[0], Ks[0], width, height,
                    sh_degree=sh_degree, background=None if backgrounds is None else backgrounds[0],
                    outputs=("rgb", "alpha"), near=near_plane, far=far_plane, track_means2d=True)
    if visibility == "gsplat":
        from visibility_compare import gsplat_visible_mask

        seen = gsplat_visible_mask(means.detach(), quats.detach(), scales.detach(), opacities.detach(),
                                   viewmats[0], Ks[0], width, height, near_plane, far_plane)
    else:
        seen = out.visible
    visible = seen.to(means.dtype)[None, :, None].expand(1, -1, 2)  # gsplat selects radii > 0
    info = {"means2d": _ScreenMeans(out.means2d), "radii": visible, "width": width, "height": height,
            "n_cameras": 1, "gaussian_ids": None}
    return out.rgb[None], out.alpha[None], info


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="scene folder (COLMAP, transforms.json or LLFF)")
    ap.add_argument("--config", default="gaussians")
    ap.add_argument("--downscale", type=int, default=None)
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--eval-every", type=int, default=500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--gsplat-src", default=None, help="folder holding gsplat's Python package (gsplat/)")
    ap.add_argument("--only", choices=("warpgs", "loop"), default=None)
    ap.add_argument("--out", default=None, help="output folder (default: a temporary one); two --only runs that "
                    "share it share the triangulated points cached there, which are not bit-reproducible between runs")
    ap.add_argument("--tag", default="")
    ap.add_argument("overrides", nargs="*", help="key=value config overrides (both sides)")
    args = ap.parse_intermixed_args(argv)
    if args.only != "warpgs":
        import_gsplat_python(args.gsplat_src, "gsplat.strategy", "strategy")
    cfg = capture_config(args.data, device=args.device, steps=args.steps, seed=args.seed, eval_every=args.eval_every,
                         config=args.config, downscale=args.downscale, overrides=args.overrides)
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        cfg.output.dir = args.out or tmp
        trainer, start, counts = initial_model(cfg)
        print(f"{Path(args.data).name}: {trainer.scene.summary()}; init {trainer.model.num_primitives} "
              f"from {trainer.init_source}", flush=True)
        if args.only != "loop":
            runs.append(run_warpgs(trainer, counts, args.eval_every))
        if args.only != "warpgs":
            runs.append(run_gsplat(cfg, args.eval_every, trainer.scene, start, rasterization=warpgs_as_gsplat,
                                   system="gsplat loop + strategy, warpgs render"))
    rows = [{"system": r["system"], "step": p["step"], "psnr": p["psnr"], "ssim": p["ssim"],
             "primitives": p["num_primitives"]} for r in runs for p in r["points"]]
    print_table(rows, ["system", "step", "psnr", "ssim", "primitives"])
    for r in runs:
        d = r["largest_drop"]
        print(f"{r['system']}: largest one-step drop {100 * d['fraction_removed']:.1f}% at step {d['step']}"
              + (f"; by rule {d['pruned_by']}" if d.get("pruned_by") else ""))
    payload = {"data": args.data, "downscale": args.downscale, "steps": args.steps, "seed": args.seed,
               "device": args.device, "runs": runs, "command": " ".join(sys.argv)}
    name = f"strategy_compare_{Path(args.data).resolve().name}_{torch.device(args.device).type}"
    name += (f"_{args.only}" if args.only else "") + (f"_{args.tag}" if args.tag else "")
    print(f"wrote {write_json(name, payload)}")
    return payload


if __name__ == "__main__":
    main()
