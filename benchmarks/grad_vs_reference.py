"""Gradients of warpgs's rasterizer against the float64 reference renderer (tests/reference.py) on a model the
Trainer has trained on a real capture, at chosen steps: the tests check the kernels on generated scenes, this checks
them on the states real training reaches (after an opacity reset, with SH degree 3, ...). Runs on the CPU.

    python benchmarks/grad_vs_reference.py data/beer --downscale 8 --at 2990,3001 --views 2 --pixels 2000

At each step in --at, for --views training views: a loss that weights --pixels sampled pixels of the rgb image at
random, differentiated through `warpgs.rasterize` (float32) and through the reference (float64, those pixels only).
Reports cosine similarity and relative L2 error per parameter, and the primitives whose sh0 gradients differ
most. Why: after the opacity reset at step 3000, warpgs's sh0/shN gradients on beer differed from gsplat's
(cos 0.95) while every other parameter's agreed to 1e-4 (benchmarks/grad_vs_gsplat.py on the GPU); this tells
which of the two departs from the exact gradient. Writes grad_vs_reference_<name>.json.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from common import ROOT, capture_config, print_table, write_json
from gradient_agreement import NAMES, agreement, render_inputs, sh0_outliers, trained_at

sys.path.insert(0, str(ROOT / "tests"))

from reference import render_reference  # noqa: E402  (the test suite's float64 oracle)

from warpgs import rasterize  # noqa: E402
from warpgs.train.trainer import Trainer  # noqa: E402


def gradients(trainer: Trainer, view, pixels: torch.Tensor, weights: torch.Tensor, chunk: int = 128) -> tuple:
    """(warpgs's gradients, the reference's) of sum(weights * rgb[pixels]) with respect to the raw parameters."""
    m, t = trainer.model, trainer.config.train
    deg = m.active_sh_degree
    ours = {k: m.params[k].detach().clone().requires_grad_(True) for k in NAMES}
    out = rasterize(*render_inputs(ours, deg), view.viewmat, view.K, view.width, view.height, sh_degree=deg,
                    background=trainer.background, outputs=("rgb",), near=t.near, far=t.far)
    (out.rgb[pixels[:, 1], pixels[:, 0]] * weights).sum().backward()
    exact = {k: m.params[k].detach().double().clone().requires_grad_(True) for k in NAMES}
    for i in range(0, len(pixels), chunk):  # the loss is a sum over pixels: chunks add up
        ref = render_reference(*render_inputs(exact, deg), view.viewmat.double(), view.K.double(), view.width,
                               view.height, sh_degree=deg, background=trainer.background.double(), near=t.near,
                               far=t.far, pixels=pixels[i:i + chunk])
        (ref["rgb"] * weights[i:i + chunk].double()).sum().backward()
    zero = torch.zeros_like
    return ({k: ours[k].grad if ours[k].grad is not None else zero(ours[k]) for k in NAMES},
            {k: exact[k].grad if exact[k].grad is not None else zero(exact[k]) for k in NAMES})


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="scene folder (COLMAP, transforms.json or LLFF)")
    ap.add_argument("--downscale", type=int, default=8)
    ap.add_argument("--at", default="2990,3001", help="comma-separated training steps to compare at")
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--pixels", type=int, default=2000, help="sampled pixels per view")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--top", type=int, default=5, help="primitives with the largest sh0 difference to list")
    ap.add_argument("--tag", default="")
    ap.add_argument("overrides", nargs="*", help="key=value config overrides")
    args = ap.parse_intermixed_args(argv)
    marks = sorted({int(s) for s in args.at.split(",")})
    cfg = capture_config(args.data, device="cpu", steps=marks[-1], seed=args.seed, downscale=args.downscale,
                         overrides=args.overrides)
    g = torch.Generator().manual_seed(args.seed)
    rows = []
    for mark, trainer, views in trained_at(cfg, marks, args.views):
        sums = None
        for v in views:
            pixels = torch.stack([torch.randint(0, v.width, (args.pixels,), generator=g),
                                  torch.randint(0, v.height, (args.pixels,), generator=g)], 1)
            weights = torch.rand(args.pixels, 3, generator=g)
            a, b = gradients(trainer, v, pixels, weights)
            sums = (a, b) if sums is None else ({k: sums[0][k] + a[k] for k in NAMES},
                                                 {k: sums[1][k] + b[k] for k in NAMES})
        row = {"step": mark, "primitives": trainer.model.num_primitives,
               "sh_degree": trainer.model.active_sh_degree, **agreement(*sums)}
        print({k: (round(v, 6) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
        row["sh0_worst"] = sh0_outliers(trainer, views[0], *sums, args.top, "reference")
        rows.append(row)
    print_table(rows, ["step", "primitives", "sh_degree"] + [f"{k}_cos" for k in NAMES] + ["sh0_rel_err"])
    name = f"grad_vs_reference_{Path(args.data).name}" + (f"_{args.tag}" if args.tag else "")
    payload = {"data": args.data, "downscale": args.downscale, "views": args.views, "pixels": args.pixels, "rows": rows}
    print(f"wrote {write_json(name, payload)}")
    return {"rows": rows}


if __name__ == "__main__":
    main()
