"""Gradients of the training loss through warpgs's rasterizer against gsplat's, on a model trained on a real capture.

    python benchmarks/grad_vs_gsplat.py data/phone64 --downscale 2 --at 2990,3001,3050 --views 8

Trains the warpgs `gaussians` recipe on the capture and, at each step in --at, renders --views training views with
both rasterizers from the same parameters and compares the gradients of the same loss (0.8 L1 + 0.2 D-SSIM) with
respect to every parameter: cosine similarity and relative L2 error, and for the opacities the share of primitives
whose summed gradient over the views points the other way, and how many each renderer would push down (the ones
an opacity reset leaves near the pruning threshold). The images' largest difference comes along. Why: after the
first opacity reset warpgs pruned 15-20% of the model where gsplat's loop pruned under 1% (issue 12,
real_capture.py); this tells a renderer difference from a strategy difference. CUDA and gsplat only.
"""
from __future__ import annotations

import argparse
import sys

import torch

from common import ROOT, print_table, write_json
from gradient_agreement import NAMES, agreement, render_inputs, sh0_outliers, trained_at

sys.path.insert(0, str(ROOT))

from warpgs.cli.commands import resolve_config_source  # noqa: E402
from warpgs.config.loader import load_config  # noqa: E402
from warpgs.metrics.image import ssim  # noqa: E402
from warpgs.train.trainer import Trainer  # noqa: E402


def loss_of(img: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return 0.8 * (img - target).abs().mean() + 0.2 * (1.0 - ssim(img, target))


def gsplat_grads(trainer: Trainer, view, rasterization) -> tuple:
    m = trainer.model
    leaves = {k: m.params[k].detach().clone().requires_grad_(True) for k in NAMES}
    deg = m.active_sh_degree
    means, quats, scales, opacities, colors = render_inputs(leaves, deg)
    t = trainer.config.train
    img, _, _ = rasterization(means, quats, scales, opacities, colors, view.viewmat[None], view.K[None],
                              view.width, view.height, sh_degree=deg, packed=False,
                              backgrounds=trainer.background[None], near_plane=t.near, far_plane=t.far)
    img = img[0]
    loss_of(img, view.image).backward()
    return img.detach(), {k: leaves[k].grad if leaves[k].grad is not None else torch.zeros_like(leaves[k]) for k in NAMES}


def warpgs_grads(trainer: Trainer, view) -> tuple:
    m = trainer.model
    m.zero_grad(set_to_none=True)
    out = trainer.render(view, ("rgb",))
    loss_of(out.rgb, view.image).backward()
    grads = {k: (m.params[k].grad.clone() if m.params[k].grad is not None else torch.zeros_like(m.params[k]))
             for k in NAMES}
    m.zero_grad(set_to_none=True)
    return out.rgb.detach(), grads


def compare(trainer: Trainer, views: list, rasterization, outliers: int = 0) -> dict:
    sums = {"warpgs": None, "gsplat": None}
    image_diff = 0.0
    for view in views:
        a_img, a = warpgs_grads(trainer, view)
        b_img, b = gsplat_grads(trainer, view, rasterization)
        image_diff = max(image_diff, float((a_img - b_img).abs().max()))
        for key, g in (("warpgs", a), ("gsplat", b)):
            sums[key] = g if sums[key] is None else {k: sums[key][k] + g[k] for k in NAMES}
    a, b = sums["warpgs"], sums["gsplat"]
    row = {"image_max_abs_diff": image_diff, **agreement(a, b)}
    if outliers:
        row["sh0_outliers"] = sh0_outliers(trainer, views[0], a, b, outliers, "gsplat")
    ga, gb = a["logit_opacities"].double(), b["logit_opacities"].double()
    scale = torch.maximum(ga.abs(), gb.abs())
    touched = scale > 1e-6 * float(scale.max().clamp_min(1e-300))
    row["opacity_touched"] = int(touched.sum())
    row["opacity_sign_disagree"] = int(((ga * gb < 0) & touched).sum())
    # Gradient descent lowers the opacities whose gradient is positive.
    row["opacity_pushed_down_warpgs"] = int((ga > 0).sum())
    row["opacity_pushed_down_gsplat"] = int((gb > 0).sum())
    return row


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="scene folder (COLMAP, transforms.json or LLFF)")
    ap.add_argument("--config", default="gaussians")
    ap.add_argument("--downscale", type=int, default=None)
    ap.add_argument("--at", default="2990,3001,3050", help="comma-separated training steps to compare at")
    ap.add_argument("--views", type=int, default=8, help="training views per comparison")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tag", default="")
    ap.add_argument("--outliers", type=int, default=0,
                    help="print the primitives whose sh0 gradients differ most (what they are: depth, opacity, ...)")
    ap.add_argument("overrides", nargs="*", help="key=value config overrides")
    args = ap.parse_intermixed_args(argv)
    try:
        from gsplat import rasterization
    except ImportError as e:
        raise SystemExit(f"gsplat is not importable ({e})")
    marks = sorted({int(s) for s in args.at.split(",")})
    overrides = [f"data.path={args.data}", "data.split=llff", "train.device=cuda", "eval.every=0",
                 f"train.seed={args.seed}", "train.progress=false", "train.checkpoint_every=0", *args.overrides]
    if args.downscale:
        overrides.append(f"data.downscale={args.downscale}")
    cfg = load_config(resolve_config_source(args.config), overrides)
    rows = []
    for mark, trainer, views in trained_at(cfg, marks, args.views):
        row = {"step": mark, "primitives": trainer.model.num_primitives,
               **compare(trainer, views, rasterization, args.outliers)}
        rows.append(row)
        print({k: (round(v, 5) if isinstance(v, float) else v) for k, v in row.items() if k != "sh0_outliers"},
              flush=True)
    print_table(rows, ["step", "primitives", "image_max_abs_diff", "logit_opacities_cos", "logit_opacities_rel_err",
                       "opacity_sign_disagree", "opacity_pushed_down_warpgs", "opacity_pushed_down_gsplat",
                       "means_cos", "log_scales_cos", "sh0_cos"])
    payload = {"data": args.data, "downscale": args.downscale, "views": args.views, "seed": args.seed,
               "rows": rows, "gpu": torch.cuda.get_device_name(), "command": " ".join(sys.argv)}
    name = f"grad_vs_gsplat_{torch.device('cuda').type}" + (f"_{args.tag}" if args.tag else "")
    print(f"wrote {write_json(name, payload)}")
    return payload


if __name__ == "__main__":
    main()
