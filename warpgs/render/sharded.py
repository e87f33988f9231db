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

from warpgs.render.defaults import DEFAULT_ALPHA_MIN
from warpgs.render.exchange import exchange_rows
from warpgs.render.gaussians import RenderOutput
from warpgs.render.splats import Splats, blend_splats, project_splats


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


def render_sharded(means, quats, scales, opacities, colors, viewmats, Ks, width: int, height: int, *,
                   sh_degree: Optional[int] = None, features: Optional[torch.Tensor] = None,
                   background: Optional[torch.Tensor] = None, outputs: Sequence[str] = ("rgb", "alpha"),
                   near: float = 0.01, far: float = 1e10, group: Optional[dist.ProcessGroup] = None,
                   track_means2d: bool = False) -> RenderOutput:
    """This rank's camera (viewmats[rank], Ks[rank]) rendered from the primitives of every rank in `group`.

    means ... features: this rank's shard, as `rasterize` takes them (every rank the same SH layout and feature
    width; a shard may be empty). viewmats [R,4,4] and Ks [R,3,3]: one camera per rank, the same tensors on every
    rank. The result is what `rasterize` gives for that camera on all primitives, up to the blend order of
    primitives at exactly equal depth; `out.visible` counts received splats, not this rank's primitives.

    track_means2d (what densification needs, per owner): `out.means2d` is then a [R, N, 2] leaf whose .grad after
    backward is dL/dmeans2d of this rank's primitives in every rank's camera, and `out.sent` the [R, N] bool mask of
    those that reached each camera's image (visible in gsplat's sense: a footprint on screen)."""
    world = dist.get_world_size(group)
    if viewmats.dim() != 3 or viewmats.shape[0] != world or Ks.shape[0] != world:
        raise ValueError(f"viewmats/Ks: expected one camera per rank ([{world},4,4] and [{world},3,3]), got "
                         f"{tuple(viewmats.shape)} and {tuple(Ks.shape)}")
    probe = means.new_zeros(world, means.shape[0], 2, requires_grad=True) if track_means2d else None
    sends, sent = [], []
    for j in range(world):
        splats = project_splats(means, quats, scales, opacities, colors, viewmats[j], Ks[j], width, height,
                                sh_degree=sh_degree, features=features, near=near, far=far)
        if probe is not None:  # adds zero; its gradient is the projected centres' (as rasterize's probe)
            splats.means2d = splats.means2d + probe[j]
        reach = reaches_image(splats, width, height)
        sent.append(reach)
        sends.append(splats.select(reach.nonzero().squeeze(1)).pack())
    received = exchange_rows(sends, group)
    out = blend_splats(Splats.unpack(torch.cat(received)), width, height, background=background, outputs=outputs)
    if probe is not None:
        out.means2d, out.sent = probe, torch.stack(sent)
    return out
