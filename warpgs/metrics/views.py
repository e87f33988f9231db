"""Held-out evaluation: render views, score them (PSNR, SSIM, LPIPS when available offline), save PNGs."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch

from warpgs.utils.atomic_file import atomic_write_bytes
from warpgs.metrics.image import LPIPSMetric, psnr, ssim


def evaluate_views(render_fn: Callable, views: Sequence, *, lpips: Optional[LPIPSMetric] = None,
                   save_dir: Optional[Path] = None) -> dict:
    """render_fn(view) -> rgb [H, W, 3]; views carry `.image` and `.name`.

    Returns {"psnr", "ssim", "lpips" (or None with "lpips_unavailable"), "num_views", "per_view": {name: {...}}};
    the means are over views. Renders are clamped to [0, 1] before scoring, as they are saved.
    """
    if not views:
        raise ValueError("views: nothing to evaluate")
    per_view = {}
    with torch.no_grad():
        for view in views:
            rgb = render_fn(view).clamp(0.0, 1.0)
            target = view.image.to(rgb)
            scores = {"psnr": float(psnr(rgb, target)), "ssim": float(ssim(rgb, target))}
            if lpips is not None and lpips.available:
                scores["lpips"] = float(lpips(rgb, target))
            per_view[view.name] = scores
            if save_dir is not None:
                from warpgs.data.formats.image_io import write_png

                write_png(Path(save_dir) / f"{Path(view.name).stem}.png", rgb.cpu().numpy())
    return summarize_views(per_view, lpips)


def summarize_views(per_view: dict, lpips=None) -> dict:
    """Means of the per-view scores ({view name: {"psnr", "ssim"[, "lpips"]}}), with the view count, the
    per-view scores and, when LPIPS is off or unavailable, why."""
    n = len(per_view)
    out = {"psnr": sum(v["psnr"] for v in per_view.values()) / n,
           "ssim": sum(v["ssim"] for v in per_view.values()) / n}
    if lpips is not None and lpips.available:
        out["lpips"] = sum(v["lpips"] for v in per_view.values()) / n
    else:
        out["lpips"] = None
        out["lpips_unavailable"] = lpips.reason if lpips is not None else "disabled (eval.lpips: false)"
    out["num_views"] = n
    out["per_view"] = per_view
    return out


def write_json(path, data: dict) -> Path:
    atomic_write_bytes(path, (json.dumps(data, indent=1, sort_keys=False) + "\n").encode())
    return Path(path)
