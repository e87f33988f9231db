"""Model-parallel rendering of 3D Gaussians: each rank holds its own share of the primitives and renders its own
camera from everybody's. Every rank projects its primitives into every rank's camera, keeps the splats that can
reach that camera's image, and sends them to its rank (an all-to-all); each rank bins and blends what it received.
Gradients take the way back: the blend adjoint on the camera's rank, the reverse all-to-all, the projection adjoint
on the primitives' owner. Memory per rank then scales with its share of the primitives, not with all of them
(docs/distributed.md, "Model parallelism")."""
from __future__ import annotations

from typing import Optional, Sequence

import torch
import torch.distributed as dist

from warpgs.render.defaults import DEFAULT_ALPHA_MAX, DEFAULT_ALPHA_MIN, DEFAULT_TRANSMITTANCE_MIN
from warpgs.render.exchange import exchange_rows
from warpgs.render.gaussians import RenderOutput
from warpgs.render.splats import Splats, blend_rows, project_rows


@torch.no_grad()
def reaches_image(splats: Splats, width: int, height: int, alpha_min: float = DEFAULT_ALPHA_MIN) -> torch.Tensor:
    """[N] bool: the splats worth sending to a camera's rank: valid, opaque enough to be blended at all, and with
    a footprint box that meets the image. The box is the binning's (alpha >= alpha_min ellipse, its axis-aligned
    extent) made a little larger, so nothing the blend would use is left behind; the rest is traffic saved."""
    opacity = splats.opacities.detach()
    q = 2.0 * torch.log(opacity.clamp_min(alpha_min) / alpha_min)
    cov = splats.cov2d
    ex = torch.sqrt(q * cov[:, 0].clamp_min(0)) * 1.01 + 1.0
    ey = torch.sqrt(q * cov[:, 2].clamp_min(0)) * 1.01 + 1.0
    x, y = splats.means2d.detach().unbind(1)
    return (splats.valid & (opacity >= alpha_min) & (x + ex >= 0) & (x - ex <= width) & (y + ey >= 0)
            & (y - ey <= height))


def render_sharded(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *,
                   sh_degree: Optional[int] = None, features: Optional[torch.Tensor] = None,
                   background: Optional[torch.Tensor] = None, outputs: Sequence[str] = ("rgb", "alpha"),
                   near: float = 0.01, far: float = 1e10, tile_size: Optional[int] = None,
                   alpha_min: float = DEFAULT_ALPHA_MIN, transmittance_min: float = DEFAULT_TRANSMITTANCE_MIN,
                   alpha_max: float = DEFAULT_ALPHA_MAX,
                   group: Optional[dist.ProcessGroup] = None, track_means2d: bool = False) -> RenderOutput:
    """This rank's camera (viewmats[rank], Ks[rank]) rendered from the primitives of every rank in `group`.

    means ... features: this rank's shard, as `rasterize` takes them (every rank the same SH layout and feature
    width; a shard may be empty). viewmats [R,4,4] and Ks [R,3,3]: one camera per rank, the same tensors on every
    rank; width and height: one size for all, or one per camera (sequences of R). The result is what `rasterize`
    gives for that camera on all primitives, up to the blend order of primitives at exactly equal depth;
    `out.visible` counts received splats, not this rank's primitives. tile_size, alpha_min, transmittance_min and
    alpha_max are the blend's, as `rasterize` takes them.

    track_means2d (what densification needs, per owner): `out.means2d` is then a [R, N, 2] leaf whose .grad after
    backward is dL/dmeans2d of this rank's primitives in every rank's camera, `out.sent` the [R, N] bool mask of
    those sent to each camera's rank, and `out.seen` [R, N] those the camera's blend binned (`rasterize`'s
    `visible`, returned to the owners by a second, small all-to-all)."""
    world, rank = dist.get_world_size(group), dist.get_rank(group)
    if viewmats.dim() != 3 or viewmats.shape[0] != world or Ks.shape[0] != world:
        raise ValueError(f"viewmats/Ks: expected one camera per rank ([{world},4,4] and [{world},3,3]), got "
                         f"{tuple(viewmats.shape)} and {tuple(Ks.shape)}")
    widths, heights = _per_camera(width, world, "width"), _per_camera(height, world, "height")
    probe = means.new_zeros(world, means.shape[0], 2, requires_grad=True) if track_means2d else None
    sends, sent, sent_rows = [], [], []
    for j in range(world):
        rows, valid = project_rows(means, quats, scales, opacities, colors, viewmats[j], Ks[j], widths[j], heights[j],
                                   sh_degree=sh_degree, features=features, near=near, far=far)
        if probe is not None:  # adds zero; its gradient is the projected centres' (as rasterize's probe)
            rows = rows + torch.nn.functional.pad(probe[j], (0, rows.shape[1] - 2))
        reach = reaches_image(Splats.unpack(rows.detach(), valid), widths[j], heights[j], alpha_min)
        picked = reach.nonzero().squeeze(1)
        sent.append(reach)
        sent_rows.append(picked)
        sends.append(rows[picked])
    received = exchange_rows(sends, group)
    out = blend_rows(torch.cat(received), widths[rank], heights[rank], background=background, outputs=outputs,
                     tile_size=tile_size, alpha_min=alpha_min, transmittance_min=transmittance_min,
                     alpha_max=alpha_max)
    if probe is not None:
        out.means2d, out.sent = probe, torch.stack(sent)
        out.seen = _binned_by_camera(out.visible, [r.shape[0] for r in received], sent_rows, means.shape[0], group)
    return out


@torch.no_grad()
def _binned_by_camera(visible: torch.Tensor, received: list, sent_rows: list, n: int, group) -> torch.Tensor:
    """[R, N] bool: which of this rank's N primitives each camera's blend binned. `visible` is this rank's blend's
    mask over the rows it received (every one valid: only valid splats are sent), `received` the block sizes
    from each rank, `sent_rows` the rows this rank sent to each camera."""
    if visible.shape[0] != sum(received):
        raise RuntimeError(f"blend visibility: {visible.shape[0]} rows for {sum(received)} received splats")
    back = list(visible.to(torch.float32)[:, None].split(received))
    returned = exchange_rows(back, group)
    seen = torch.zeros(len(sent_rows), n, dtype=torch.bool, device=visible.device)
    for j, rows in enumerate(sent_rows):
        seen[j, rows] = returned[j][:, 0] > 0.5
    return seen


def _per_camera(size, world: int, name: str) -> list:
    """An image size for each of the `world` cameras, from one int or a sequence of them."""
    sizes = [int(size)] * world if isinstance(size, (int, float)) else [int(v) for v in size]
    if len(sizes) != world or min(sizes) <= 0:
        raise ValueError(f"{name}: expected a positive size or one per rank ({world}), got {size!r}")
    return sizes
