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
import tempfile
from pathlib import Path

import torch

from common import ROOT, capture_config, print_table, write_json

sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from reference import render_reference, sh_to_rgb  # noqa: E402  (the test suite's float64 oracle)

from warpgs import rasterize  # noqa: E402
from warpgs.train.trainer import Trainer  # noqa: E402

NAMES = ("means", "log_scales", "quats", "logit_opacities", "sh0", "shN")


def render_inputs(params: dict, degree: int) -> tuple:
    """(means, quats, scales, opacities, SH coefficients) as the op takes them, from the model's raw parameters."""
    k = (degree + 1) ** 2
    colors = torch.cat([params["sh0"], params["shN"][:, : k - 1]], 1)
    return (params["means"], params["quats"], torch.exp(params["log_scales"]), torch.sigmoid(params["logit_opacities"]),
            colors)


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


def compare(a: dict, b: dict, top: int, trainer: Trainer, view) -> dict:
    row = {}
    for k in NAMES:
        x, y = a[k].double().flatten(), b[k].double().flatten()
        row[f"{k}_cos"] = float(x @ y / (x.norm() * y.norm()).clamp_min(1e-300))
        row[f"{k}_rel_err"] = float((x - y).norm() / y.norm().clamp_min(1e-300))
    diff = (a["sh0"].double() - b["sh0"]).reshape(len(b["sh0"]), -1).norm(dim=1)
    idx = diff.topk(min(top, len(diff))).indices
    row["sh0_worst"] = [{"index": int(i), "diff": float(diff[i]), "warpgs": a["sh0"][i].flatten().tolist(),
                         "reference": b["sh0"][i].flatten().tolist(),
                         "means_grad_warpgs": a["means"][i].tolist(), "means_grad_reference": b["means"][i].tolist(),
                         "opacity_grad_warpgs": float(a["logit_opacities"][i]),
                         "opacity_grad_reference": float(b["logit_opacities"][i]),
                         **describe(trainer, view, int(i))} for i in idx]
    return row


@torch.no_grad()
def describe(trainer: Trainer, view, i: int) -> dict:
    """What primitive i is, seen from the first view: camera depth, pixel position, opacity, scales, and its colour
    before the clamp at 0 (SH + 0.5)."""
    m = trainer.model
    p = m.means[i] @ view.viewmat[:3, :3].T + view.viewmat[:3, 3]
    centre = -view.viewmat[:3, :3].T @ view.viewmat[:3, 3]
    d = m.means[i] - centre
    sh = torch.cat([m.params["sh0"][i], m.params["shN"][i]], 0)[None].double()
    rgb = sh_to_rgb(sh, m.active_sh_degree, (d / d.norm())[None].double())[0]
    return {"depth": float(p[2]), "u": float(view.K[0, 0] * p[0] / p[2] + view.K[0, 2]),
            "v": float(view.K[1, 1] * p[1] / p[2] + view.K[1, 2]), "opacity": float(m.opacities[i]),
            "scales": m.scales[i].tolist(), "colour_clamped_at_0": rgb.tolist()}


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
    with tempfile.TemporaryDirectory() as tmp:
        cfg.output.dir = tmp
        trainer = Trainer(cfg, quiet=True)
        views = [trainer.view(i) for i in trainer.scene.train[: args.views]]
        for mark in marks:
            while trainer.step < mark:
                trainer.train_step()
            trainer.model.active_sh_degree = min(trainer.model.max_sh_degree, mark // max(cfg.model.sh_interval, 1))
            sums = None
            for v in views:
                pixels = torch.stack([torch.randint(0, v.width, (args.pixels,), generator=g),
                                      torch.randint(0, v.height, (args.pixels,), generator=g)], 1)
                weights = torch.rand(args.pixels, 3, generator=g)
                a, b = gradients(trainer, v, pixels, weights)
                sums = (a, b) if sums is None else ({k: sums[0][k] + a[k] for k in NAMES},
                                                     {k: sums[1][k] + b[k] for k in NAMES})
            row = {"step": mark, "primitives": trainer.model.num_primitives,
                   "sh_degree": trainer.model.active_sh_degree, **compare(*sums, args.top, trainer, views[0])}
            rows.append(row)
            print({k: (round(v, 6) if isinstance(v, float) else v) for k, v in row.items() if k != "sh0_worst"},
                  flush=True)
            for w in row["sh0_worst"]:
                print("   ", w, flush=True)
    print_table(rows, ["step", "primitives", "sh_degree"] + [f"{k}_cos" for k in NAMES] + ["sh0_rel_err"])
    name = f"grad_vs_reference_{Path(args.data).name}" + (f"_{args.tag}" if args.tag else "")
    print(f"wrote {write_json(name, {'data': args.data, 'downscale': args.downscale, 'views': args.views, 'pixels': args.pixels, 'rows': rows})}")
    return {"rows": rows}


if __name__ == "__main__":
    main()
