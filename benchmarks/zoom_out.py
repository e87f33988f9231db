"""Held-out quality when a trained run is rendered smaller than it was trained: PSNR of the test views at 1, 1/2 and
1/4 of the training resolution against the test images box-filtered to that size (what a thumbnail, a zoomed-out
viewer or a lower-resolution video shows).

    python benchmarks/zoom_out.py RUN [RUN ...] [--factors 1,2,4] [--device cpu] [--tag NAME]

Each run is scored twice: with the screen-space filter scaled to the image (what the renders do: surfels' fallback
width, warpgs.model.rendering.surfel_screen_sigma; 3D Gaussians' low-pass, gaussian_low_pass) and fixed in the
pixels of every image (2DGS's 1/sqrt(2) px, 3DGS's 0.3 px²), which dilates every primitive seen smaller than in
training. Writes benchmarks/results/zoom_out[_<tag>].json.
"""
from __future__ import annotations

import argparse
import copy
import sys

import torch
import torch.nn.functional as F

from common import ROOT, print_table, write_json


def psnr_at(trainer, factor: int) -> float:
    from warpgs.metrics.image import psnr

    scores = []
    for i in trainer.scene.test or trainer.scene.train:
        view = trainer.scene.view(i, trainer.device)
        w, h = view.width // factor, view.height // factor
        small = copy.copy(view)
        K = view.K.clone()
        K[:2] /= factor  # pixel centres at i + 0.5: a factor-f box of the full image is one pixel of the small one
        small.K, small.width, small.height = K, w, h
        target = F.avg_pool2d(view.image[:h * factor, :w * factor].permute(2, 0, 1)[None], factor)[0].permute(1, 2, 0)
        with torch.no_grad():
            rgb = trainer.render(small, ("rgb",)).rgb.clamp(0.0, 1.0)
        scores.append(float(psnr(rgb, target)))
    return sum(scores) / len(scores)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="warpgs-train output folders")
    ap.add_argument("--factors", default="1,2,4", help="downscale factors of the renders")
    ap.add_argument("--device", default=None, help="default: each run's")
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    from warpgs.cli.commands import load_run

    factors = [int(f) for f in args.factors.split(",")]
    rows = []
    for run in args.runs:
        trainer = load_run(run, args.device)
        focal = trainer.training_focal
        for mode in ("scaled", "fixed"):
            trainer.training_focal = None if mode == "fixed" else focal  # None: the ops' default filter
            row = {"run": str(run), "kind": trainer.model.kind, "primitives": trainer.model.num_primitives,
                   "filter": mode}
            row.update({f"psnr_1/{f}": round(psnr_at(trainer, f), 3) for f in factors})
            rows.append(row)
        trainer.training_focal = focal
    print_table(rows, list(rows[0]))
    payload = {"rows": rows, "factors": factors, "command": " ".join(sys.argv)}
    print(f"-> {write_json('zoom_out' + (f'_{args.tag}' if args.tag else ''), payload)}")
    return payload


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main()
