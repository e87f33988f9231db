"""Render time of a model trained on a real capture, warpgs against gsplat, on the capture's held-out cameras.

    python benchmarks/raster_trained.py data/phone64 --downscale 2 --device cuda --steps 7000 --gsplat

Trains `warpgs-train gaussians` for --steps on DIR (any scene warpgs-train reads), then times, for each of the
first --views test cameras, a forward (rgb + expected depth, SH at the model's degree) and a forward+backward of
Σ rgb·g + Σ depth·g' with warpgs.rasterize and (with --gsplat, CUDA) gsplat.rasterization(render_mode="RGB+ED") on
the same parameters, in interleaved rounds in one process (medians). Unlike benchmarks/raster.py's random scenes,
the sizes, opacities and overlaps are those training produced. Writes raster_trained_<name>_<device>.json.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

import torch

from common import ROOT, capture_config, print_table, time_call, write_json

sys.path.insert(0, str(ROOT))

from warpgs import rasterize  # noqa: E402
from warpgs.train.trainer import Trainer  # noqa: E402


def trained_model(args) -> Trainer:
    cfg = capture_config(args.data, device=args.device, steps=args.steps, downscale=args.downscale,
                         overrides=args.overrides)
    cfg.output.dir = args.out
    trainer = Trainer(cfg, quiet=True)
    trainer.fit()
    return trainer


def renderers(params: dict, view, sh_degree: int, background: torch.Tensor):
    """{"warpgs": (fwd, fwd_bwd), "gsplat": ...}: closures over one camera; each backward uses fixed weights."""
    g = torch.Generator().manual_seed(0)
    w_rgb = torch.rand(view.height, view.width, 3, generator=g).to(params["means"].device)
    w_depth = torch.rand(view.height, view.width, 1, generator=g).to(params["means"].device)

    def leaves(grad: bool):
        return {k: v.detach().requires_grad_(grad) for k, v in params.items()}

    def ours(p):
        out = rasterize(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"], view.viewmat, view.K,
                        view.width, view.height, sh_degree=sh_degree, background=background,
                        outputs=("rgb", "depth"), check_inputs=False)
        return out.rgb, out.depth

    def theirs(p):
        import gsplat

        img, _, _ = gsplat.rasterization(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"],
                                         view.viewmat[None], view.K[None], view.width, view.height,
                                         sh_degree=sh_degree, packed=False, render_mode="RGB+ED",
                                         backgrounds=background[None])  # gsplat appends the depth channel's 0
        return img[0, ..., :3], img[0, ..., 3:]

    def timed(render):
        def fwd():
            return render(leaves(False))

        def fwd_bwd():
            rgb, depth = render(leaves(True))
            ((rgb * w_rgb).sum() + (depth * w_depth).sum()).backward()
        return fwd, fwd_bwd

    return {"warpgs": (timed(ours), ours), "gsplat": (timed(theirs), theirs)}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", help="scene folder (COLMAP, transforms.json or LLFF)")
    ap.add_argument("--downscale", type=int, default=None)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--steps", type=int, default=7000, help="training steps before timing")
    ap.add_argument("--views", type=int, default=3, help="held-out cameras to time")
    ap.add_argument("--rounds", type=int, default=7, help="interleaved rounds; each times 10 calls")
    ap.add_argument("--gsplat", action="store_true", help="time gsplat.rasterization side by side (CUDA)")
    ap.add_argument("overrides", nargs="*", help="key=value config overrides")
    args = ap.parse_intermixed_args(argv)
    if args.gsplat and not args.device.startswith("cuda"):
        raise SystemExit("--gsplat: gsplat's rasterizer runs on CUDA only (use --device cuda)")
    systems = ["warpgs"] + (["gsplat"] if args.gsplat else [])
    with tempfile.TemporaryDirectory() as tmp:
        args.out = tmp
        trainer = trained_model(args)
        model = trainer.model
        inputs = model.render_inputs()
        sh_degree = inputs.pop("sh_degree")
        params = {k: v.detach() for k, v in inputs.items()}
        views = [trainer.scene.view(i, trainer.device) for i in (trainer.scene.test or trainer.scene.train)[:args.views]]
        rows = []
        for view in views:
            closures = renderers(params, view, sh_degree, trainer.background)
            times = {s: {"fwd": [], "fwd_bwd": []} for s in systems}
            for _ in range(args.rounds):
                for s in systems:
                    (fwd, fwd_bwd), _ = closures[s]
                    times[s]["fwd"].append(time_call(fwd, args.device, warmup=2, repeats=10))
                    times[s]["fwd_bwd"].append(time_call(fwd_bwd, args.device, warmup=2, repeats=10))
            row = {"view": view.name, "size": f"{view.width}x{view.height}", "primitives": model.num_primitives}
            for s in systems:
                row[f"{s}_fwd_ms"] = statistics.median(times[s]["fwd"])
                row[f"{s}_fwd_bwd_ms"] = statistics.median(times[s]["fwd_bwd"])
            if args.gsplat:
                row["ratio_fwd"] = row["warpgs_fwd_ms"] / row["gsplat_fwd_ms"]
                row["ratio_fwd_bwd"] = row["warpgs_fwd_bwd_ms"] / row["gsplat_fwd_bwd_ms"]
                with torch.no_grad():
                    a, b = closures["warpgs"][1](params)[0], closures["gsplat"][1](params)[0]
                row["max_rgb_diff"] = float((a - b).abs().max())
                row["mean_rgb_diff"] = float((a - b).abs().mean())
            rows.append(row)
    print_table(rows, list(rows[0]))
    name = f"raster_trained_{Path(args.data).resolve().name}_{torch.device(args.device).type}"
    payload = {"data": args.data, "steps": args.steps, "downscale": args.downscale, "sh_degree": sh_degree,
               "rows": rows, "command": " ".join(sys.argv)}
    if args.device.startswith("cuda"):
        payload["gpu"] = torch.cuda.get_device_name()
    print(f"wrote {write_json(name, payload)}")
    return payload


if __name__ == "__main__":
    main()
