"""The maps a trained model renders besides colour (depth, normals, alpha), chosen per primitive kind, and the
colours that show them (warpgs-render's previews, warpgs-view's display modes).

depth: the surface depth along the camera's z axis. Surfels give their median depth (where the accumulated
opacity crosses 0.5: the 2DGS surface); 3D Gaussians the expected depth (Σ w z / alpha), which blurs depth
edges. normal: surfels only, world space, facing the camera. A pixel's depth and normal are valid where its
alpha reaches VALID_ALPHA (half covered).
"""
from __future__ import annotations

from typing import Sequence, Tuple

import torch

from warpgs.model.rendering import check_outputs

MAPS = ("rgb", "depth", "normal", "alpha")
VALID_ALPHA = 0.5
_QUANTILE_SAMPLE = 1 << 20
# Our own ramp for depth previews, near to far: light yellow, orange, red, purple, dark blue.
_RAMP = torch.tensor([[1.00, 0.95, 0.60], [0.98, 0.65, 0.20], [0.85, 0.25, 0.20], [0.50, 0.10, 0.45],
                      [0.10, 0.08, 0.30]])


def depth_output(kind: str) -> str:
    """The render op output that holds a kind's surface depth."""
    return "median_depth" if kind == "surfels" else "depth"


def parse_maps(text: str, who: str = "--outputs") -> Tuple[str, ...]:
    """'rgb,depth' -> ("rgb", "depth"), in the order given; ValueError naming `who` for an unknown name."""
    names = tuple(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
    unknown = [n for n in names if n not in MAPS]
    if not names or unknown:
        raise ValueError(f"{who}: expected a comma-separated list of {list(MAPS)}, got {text!r}")
    return names


def render_outputs(kind: str, maps: Sequence[str], who: str = "--outputs") -> Tuple[str, ...]:
    """The render op outputs `maps` need for a model of `kind` (alpha too for depth and normals: it says where
    they are valid); ValueError naming `who` when the kind cannot render one of them."""
    wanted = {"rgb": "rgb", "alpha": "alpha", "depth": depth_output(kind), "normal": "normal"}
    outputs = [wanted[m] for m in maps]
    check_outputs(kind, outputs, who)
    if any(m in ("depth", "normal") for m in maps):
        outputs.append("alpha")
    return tuple(dict.fromkeys(outputs))


def valid_pixels(alpha: torch.Tensor) -> torch.Tensor:
    """[H, W] bool from an [H, W, 1] alpha."""
    return alpha[..., 0] >= VALID_ALPHA


def depth_colours(depth: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """[H, W] depth -> [H, W, 3] colours in [0, 1]: inverse depth stretched over the 2nd..98th percentile of the
    valid pixels (so a few stray near or far ones do not flatten the rest), black where not valid."""
    depth = depth.reshape(valid.shape).float()
    out = depth.new_zeros(*valid.shape, 3)
    ok = valid & (depth > 0) & torch.isfinite(depth)
    if not ok.any():
        return out
    inv = 1.0 / depth[ok]
    lo, hi = stretch_range(inv)
    t = ((hi - inv) / max(hi - lo, 1e-12)).clamp(0, 1)  # 0 near, 1 far
    ramp = _RAMP.to(depth.device)
    x = t * (len(ramp) - 1)
    i = x.floor().long().clamp(max=len(ramp) - 2)
    f = (x - i)[:, None]
    out[ok] = ramp[i] * (1 - f) + ramp[i + 1] * f
    return out


def stretch_range(values: torch.Tensor) -> Tuple[float, float]:
    """The 2nd and 98th percentiles of a 1-D tensor, from at most _QUANTILE_SAMPLE evenly strided values (enough
    for a colour ramp; torch.quantile refuses more than 2^24 values, fewer than a 6000x4000 photo's pixels)."""
    step = -(-values.numel() // _QUANTILE_SAMPLE)
    qs = torch.tensor([0.02, 0.98], dtype=values.dtype, device=values.device)
    lo, hi = torch.quantile(values[::step], qs).tolist()
    return lo, hi


def normal_colours(normal: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """[H, W, 3] normals (any length) -> colours (n / |n| + 1) / 2 in [0, 1], black where not valid."""
    n = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.where(valid[..., None], (n + 1) * 0.5, torch.zeros_like(n))


def display_image(out, kind: str, mode: str) -> torch.Tensor:
    """An [H, W, 3] image in [0, 1] of one render `out` (asked for render_outputs(kind, [mode])): colour, depth or
    normals coloured, or alpha as grey."""
    if mode == "rgb":
        return out.rgb
    if mode == "alpha":
        return out.alpha.expand(*out.alpha.shape[:-1], 3)
    valid = valid_pixels(out.alpha)
    if mode == "depth":
        return depth_colours(getattr(out, depth_output(kind))[..., 0], valid)
    if mode == "normal":
        return normal_colours(out.normal, valid)
    raise ValueError(f"display mode: expected one of {list(MAPS)}, got {mode!r}")
