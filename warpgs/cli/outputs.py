"""`warpgs-render --outputs rgb,depth,normal,alpha`: the files of one rendered view (model/maps.py picks the maps).

    <stem>.png                 colour (8-bit)
    <stem>_depth.exr           depth, float32 EXR (channel Z, a `valid` channel; data/depth/files.py reads it)
    <stem>_depth.png           depth x depth_scale as 16-bit PNG, 0 where there is none (default scale 1000:
                               millimetres when the scene is in metres; read_depth(..., scale=1/1000) reads it)
    <stem>_depth_preview.png   depth coloured for a look (near yellow to far blue)
    <stem>_normal.exr          world-space unit normals, float32 EXR (channels normal.R/G/B = x/y/z; 0 where none)
    <stem>_normal.png          the same as colours, (n + 1) / 2
    <stem>_alpha.png           accumulated opacity (8-bit)
All files are written atomically.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import torch

from warpgs.data.depth.files import write_depth_png16, write_exr, write_exr_channels
from warpgs.data.formats.image_io import write_png
from warpgs.model.maps import depth_colours, depth_output, normal_colours, valid_pixels

DEFAULT_DEPTH_SCALE = 1000.0


@dataclass
class MapStats:
    files: int = 0
    depth_beyond_png: int = 0  # valid depth pixels too far for the 16-bit PNG (written as 0 there; the EXR has them)


def write_maps(out_dir: Path, stem: str, maps: Sequence[str], out, kind: str, stats: MapStats,
               depth_scale: float = DEFAULT_DEPTH_SCALE) -> None:
    """Write the files of `maps` for one render `out` (asked for model.maps.render_outputs(kind, maps))."""
    out_dir = Path(out_dir)
    valid = valid_pixels(out.alpha) if ("depth" in maps or "normal" in maps) else None
    if "rgb" in maps:
        write_png(out_dir / f"{stem}.png", out.rgb.clamp(0, 1).cpu().numpy())
        stats.files += 1
    if "depth" in maps:
        depth = getattr(out, depth_output(kind))[..., 0]
        ok = valid & torch.isfinite(depth) & (depth > 0)
        d = torch.where(ok, depth, torch.zeros_like(depth)).cpu().numpy()
        write_exr(out_dir / f"{stem}_depth.exr", d, "depth", valid=ok.cpu().numpy())
        stats.depth_beyond_png += write_depth_png16(out_dir / f"{stem}_depth.png", d, depth_scale, ok.cpu().numpy())
        write_png(out_dir / f"{stem}_depth_preview.png", depth_colours(depth, ok).cpu().numpy())
        stats.files += 3
    if "normal" in maps:
        n = out.normal / out.normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        n = torch.where(valid[..., None], n, torch.zeros_like(n))
        write_exr_channels(out_dir / f"{stem}_normal.exr", {"normal": n.cpu().numpy()})
        write_png(out_dir / f"{stem}_normal.png", normal_colours(n, valid).cpu().numpy())
        stats.files += 2
    if "alpha" in maps:
        write_png(out_dir / f"{stem}_alpha.png", out.alpha[..., 0].clamp(0, 1).cpu().numpy())
        stats.files += 1
