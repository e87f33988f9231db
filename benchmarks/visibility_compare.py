"""Which primitives count as seen for the densification statistics: warpgs's `visible` (the primitive reaches a
tile) against gsplat 1.5.3's rule (radii > 0: opacity at least 1/255, its opacity-aware 3.33-sigma box meets the
image, depth within near/far), on the Trainer's model after --steps steps, over every training view. Runs on the
CPU; gsplat's Python sources give the projection (--gsplat-src, as benchmarks/strategy_compare.py).

    python benchmarks/visibility_compare.py data/beer --downscale 8 --seed 2 --steps 2000 --gsplat-src /path/to/gsplat-1.5.3

Reports the primitive-view pairs each rule counts, and the densification candidates (mean NDC-gradient norm over
the views counted, against strategy.grad_threshold) that each count gives for the same gradients: the average
divides by the count, so a rule that counts more views lowers it. Writes visibility_compare_<name>.json.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import torch

from common import ROOT, capture_config, import_gsplat_python, write_json

sys.path.insert(0, str(ROOT))

from warpgs.train.trainer import Trainer  # noqa: E402

ALPHA_THRESHOLD = 1.0 / 255.0  # gsplat's, and warpgs's default alpha_min
MAX_EXTENT = 3.33  # gsplat's box half-size in standard deviations, before the opacity-aware shrink


@torch.no_grad()
def gsplat_visible(model, view, near: float, far: float) -> torch.Tensor:
    """[N] bool: gsplat 1.5.3's radii > 0 for the model seen from one view (`gsplat_visible_mask`)."""
    return gsplat_visible_mask(model.means, model.quats, model.scales, model.opacities.detach(), view.viewmat,
                               view.K, view.width, view.height, near, far)


@torch.no_grad()
def gsplat_visible_mask(means, quats, scales, opacity, viewmat, K, width: int, height: int, near: float,
                        far: float) -> torch.Tensor:
    """[N] bool: gsplat 1.5.3's radii > 0 for one camera (ProjectionEWA3DGSFused.cu, without compensation). The
    torch reference gives the blurred 2D covariance; the opacity-aware shrink of the box is the CUDA kernel's."""
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci

    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False, triu=False)
    radii, means2d, _, conics, _ = _fully_fused_projection(means[None], covars[None], viewmat[None, None],
                                                           K[None, None], width, height, near_plane=near,
                                                           far_plane=far)
    extent = torch.sqrt(2.0 * torch.log(torch.clamp(opacity / ALPHA_THRESHOLD, min=1.0))).clamp(max=MAX_EXTENT)
    a, b, c = conics[0, 0].unbind(-1)  # the inverse of the blurred covariance [[a, b], [b, c]]
    det = a * c - b * b
    rx, ry = torch.ceil(extent * torch.sqrt(c / det)), torch.ceil(extent * torch.sqrt(a / det))
    mx, my = means2d[0, 0].unbind(-1)
    inside = (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
    return (radii[0, 0] > 0).all(-1) & (opacity >= ALPHA_THRESHOLD) & inside & ((rx > 0) | (ry > 0))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="scene folder (COLMAP, transforms.json or LLFF)")
    ap.add_argument("--downscale", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=2000, help="training steps before comparing")
    ap.add_argument("--gsplat-src", default=None, help="folder holding gsplat's Python package (gsplat/)")
    ap.add_argument("overrides", nargs="*", help="key=value config overrides")
    args = ap.parse_intermixed_args(argv)
    import_gsplat_python(args.gsplat_src, "gsplat.cuda._torch_impl", "torch projection")
    cfg = capture_config(args.data, device="cpu", steps=max(args.steps, 1), seed=args.seed, downscale=args.downscale,
                         overrides=args.overrides)
    with tempfile.TemporaryDirectory() as tmp:
        cfg.output.dir = tmp
        trainer = Trainer(cfg, quiet=True)
        while trainer.step < args.steps:
            trainer.train_step()
        model, n = trainer.model, trainer.model.num_primitives
        pairs = {"both": 0, "warpgs_only": 0, "gsplat_only": 0}
        grads = {"warpgs": torch.zeros(n), "gsplat": torch.zeros(n)}
        counts = {"warpgs": torch.zeros(n), "gsplat": torch.zeros(n)}
        for i in trainer.train_indices:
            view = trainer.view(i)
            batch = trainer.make_batch(view, args.steps)
            out = trainer.render(view, trainer.outputs_at(args.steps), batch, track_means2d=True, step=args.steps)
            trainer.loss_set(out, batch, model, args.steps, trainer.max_steps).total.backward()
            model.zero_grad(set_to_none=True)
            norms = (out.means2d.grad * torch.tensor([0.5 * view.width, 0.5 * view.height])).norm(dim=-1)
            seen = {"warpgs": out.visible.detach().bool(),
                    "gsplat": gsplat_visible(model, view, cfg.train.near, cfg.train.far)}
            pairs["both"] += int((seen["warpgs"] & seen["gsplat"]).sum())
            pairs["warpgs_only"] += int((seen["warpgs"] & ~seen["gsplat"]).sum())
            pairs["gsplat_only"] += int((~seen["warpgs"] & seen["gsplat"]).sum())
            for rule, mask in seen.items():
                grads[rule] += torch.where(mask, norms, torch.zeros_like(norms))
                counts[rule] += mask.float()
    threshold = cfg.strategy.grad_threshold
    candidates = {rule: (grads[rule] / counts[rule].clamp_min(1)) >= threshold for rule in grads}
    result = {"data": args.data, "downscale": args.downscale, "seed": args.seed, "steps": args.steps,
              "primitives": n, "views": len(trainer.train_indices), "pairs": pairs,
              "mean_views_counted": {r: float(c.mean()) for r, c in counts.items()},
              "densify_candidates": {r: int(c.sum()) for r, c in candidates.items()},
              "candidates_in_both": int((candidates["warpgs"] & candidates["gsplat"]).sum()),
              "command": " ".join(sys.argv)}
    total = sum(pairs.values())
    print(f"{n} primitives after {args.steps} steps, {result['views']} training views")
    print(f"  primitive-view pairs: both {pairs['both']}, warpgs only {pairs['warpgs_only']}, gsplat only "
          f"{pairs['gsplat_only']} ({100.0 * pairs['gsplat_only'] / max(total, 1):.2f}%)")
    print(f"  densification candidates with each count: warpgs {result['densify_candidates']['warpgs']}, gsplat "
          f"{result['densify_candidates']['gsplat']}, both {result['candidates_in_both']}")
    name = f"visibility_compare_{Path(args.data).resolve().name}_s{args.seed}_step{args.steps}"
    print(f"wrote {write_json(name, result)}")
    return result


if __name__ == "__main__":
    main()
