"""The 3D Gaussian render op cut in two at the projected splats, for renders whose primitives do not all live in
one process (model-parallel training: docs/distributed.md). `project_splats` turns 3D Gaussians into the 2D
splats one camera sees; `blend_splats` bins and blends splats gathered from anywhere. Both are torch autograd
ops over the same Warp stages as `rasterize` (general pipeline), so `blend_splats(project_splats(...))` renders
and differentiates what `rasterize` does (tests/test_render_splats.py)."""
from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass
from typing import Optional, Sequence

import torch
import warp as wp

from warpgs.render import pipeline_gaussians as pipeline
from warpgs.render.defaults import DEFAULT_ALPHA_MAX, DEFAULT_ALPHA_MIN, DEFAULT_TILE_SIZE, DEFAULT_TRANSMITTANCE_MIN
from warpgs.render.gaussians import (OUTPUTS, RenderOutput, _intrinsics_vector, _to_wp, _zero_grad,
                                     blended_images, check_blend_knobs, checked_call, on_torch_stream,
                                     raster_settings, set_image_outputs, upstream_image_gradients)

# Float columns of a packed splat row (pack / unpack): means2d 2, conics 3, cov2d 3, depth 1, colour 3, opacity 1,
# then the features.
SPLAT_COLUMNS = 13


@dataclass
class Splats:
    """N projected 3D Gaussians as one camera sees them (rows line up with the primitives they came from).
    cov2d and valid steer binning only and carry no gradient."""

    means2d: torch.Tensor  # [N, 2] pixels
    conics: torch.Tensor  # [N, 3] inverse 2D covariance (a, b, c)
    cov2d: torch.Tensor  # [N, 3]
    depths: torch.Tensor  # [N] camera z
    colors: torch.Tensor  # [N, 3] evaluated colour (SH at this camera)
    valid: torch.Tensor  # [N] bool: in front of the near plane and projectable
    opacities: torch.Tensor  # [N]
    features: torch.Tensor  # [N, C] (C may be 0)

    def pack(self) -> torch.Tensor:
        """[N, 13 + C] float rows, differentiable in every column but cov2d (for exchanging between ranks)."""
        return torch.cat([self.means2d, self.conics, self.cov2d.detach(), self.depths[:, None], self.colors,
                          self.opacities[:, None], self.features], dim=1)

    @staticmethod
    def unpack(rows: torch.Tensor) -> "Splats":
        """The inverse of pack for rows that are all valid."""
        return Splats(means2d=rows[:, 0:2], conics=rows[:, 2:5], cov2d=rows[:, 5:8].detach(), depths=rows[:, 8],
                      colors=rows[:, 9:12], valid=torch.ones(rows.shape[0], dtype=torch.bool, device=rows.device),
                      opacities=rows[:, 12], features=rows[:, SPLAT_COLUMNS:])

    def select(self, rows: torch.Tensor) -> "Splats":
        return Splats(*(getattr(self, f)[rows] for f in ("means2d", "conics", "cov2d", "depths", "colors", "valid",
                                                          "opacities", "features")))


class _ProjectFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, settings, means, quats, scales, coeffs, viewmat, intrinsics):
        needs = ctx.needs_input_grad[1:7]
        inputs = (means, quats, scales, coeffs, viewmat, intrinsics)
        grads = [_zero_grad(t) if need else None for t, need in zip(inputs, needs)]
        w_means = _to_wp(means, wp.vec3, grads[0])
        w_quats = _to_wp(quats, wp.vec4, grads[1])
        w_scales = _to_wp(scales, wp.vec3, grads[2])
        w_coeffs = _to_wp(coeffs, wp.vec3, grads[3])
        w_view = _to_wp(viewmat.reshape(1, 4, 4), wp.mat44, None if grads[4] is None else grads[4].view(1, 4, 4))
        w_intr = _to_wp(intrinsics.reshape(1, 4), wp.vec4, None if grads[5] is None else grads[5].view(1, 4))
        tape = wp.Tape()
        differentiable = any(needs) and means.shape[0] > 0  # Warp has no grads for empty arrays
        with tape if differentiable else nullcontext():
            proj = pipeline.project_gaussians(w_means, w_quats, w_scales, None, w_coeffs, w_view, w_intr, settings,
                                              requires_grad=differentiable)
        ctx.state = (tape, proj, grads, differentiable)
        valid = wp.to_torch(proj.valid) > 0
        cov2d = wp.to_torch(proj.cov2d).view(-1, 3)
        ctx.mark_non_differentiable(valid, cov2d)
        ctx.device = means.device
        return (wp.to_torch(proj.means2d).view(-1, 2), wp.to_torch(proj.conics).view(-1, 3), cov2d,
                wp.to_torch(proj.depths), wp.to_torch(proj.colors).view(-1, 3), valid)

    @staticmethod
    def backward(ctx, g_means2d, g_conics, _g_cov2d, g_depths, g_colors, _g_valid):
        tape, proj, grads, differentiable = ctx.state
        ctx.state = None
        if differentiable:
            upstream = {}
            for array, g, dtype in ((proj.means2d, g_means2d, wp.vec2), (proj.conics, g_conics, wp.vec3),
                                    (proj.depths, g_depths, wp.float32), (proj.colors, g_colors, wp.vec3)):
                if g is not None:
                    upstream[array] = wp.from_torch(g.contiguous(), dtype=dtype)
            with on_torch_stream(ctx.device):
                tape.backward(grads=upstream)
        return (None,) + tuple(grads)


class _BlendFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, settings, wanted, means2d, conics, cov2d, depths, colors, opacities, features):
        needs = ctx.needs_input_grad
        learn = any(needs[2:])
        n = means2d.shape[0]
        learn_rows = learn and n > 0
        grads = {name: (_zero_grad(t) if learn_rows else None)
                 for name, t in (("means2d", means2d), ("conics", conics), ("depths", depths), ("colors", colors),
                                 ("opacities", opacities), ("features", features))}
        proj = pipeline.Projected(
            means2d=_to_wp(means2d, wp.vec2, grads["means2d"]), conics=_to_wp(conics, wp.vec3, grads["conics"]),
            cov2d=_to_wp(cov2d, wp.vec3), depths=_to_wp(depths, wp.float32, grads["depths"]),
            colors=_to_wp(colors, wp.vec3, grads["colors"]),
            valid=wp.from_torch(torch.ones(n, dtype=torch.int32, device=means2d.device)))
        w_opac = _to_wp(opacities, wp.float32, grads["opacities"])
        w_feat = _to_wp(features, wp.float32, grads["features"])
        bins = pipeline.bin_gaussians(proj, w_opac, settings)
        fwd = pipeline.blend_forward(proj, bins, w_opac, w_feat, settings, wanted)
        color, alpha, depth, inv_depth, feats = blended_images(fwd, settings, wanted)
        visible = wp.to_torch(bins.counts) > 0
        ctx.mark_non_differentiable(visible)
        ctx.state = (proj, bins, fwd, w_opac, w_feat, settings, wanted, grads, learn_rows)
        ctx.device = means2d.device
        empty = means2d.new_zeros(0)
        return tuple(empty if o is None else o for o in (color, alpha, depth, inv_depth, feats)) + (visible,)

    @staticmethod
    def backward(ctx, g_color, g_alpha, g_depth, g_inv, g_feat, _g_visible):
        proj, bins, fwd, w_opac, w_feat, settings, wanted, grads, learn_rows = ctx.state
        ctx.state = None
        if learn_rows:
            with on_torch_stream(ctx.device):
                gc, ga, gd, gi, gf = upstream_image_gradients(g_color, g_alpha, g_depth, g_inv, g_feat, settings,
                                                              wanted, ctx.device)
                pipeline.blend_backward(proj, bins, w_opac, w_feat, settings, wanted, fwd, gc, ga, gd, gi, gf)
        g = grads
        return (None, None, g["means2d"], g["conics"], None, g["depths"], g["colors"], g["opacities"], g["features"])


def project_splats(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *,
                   sh_degree: Optional[int] = None, features: Optional[torch.Tensor] = None, near: float = 0.01,
                   far: float = 1e10) -> Splats:
    """The splats of N 3D Gaussians seen from one camera (viewmat [4,4], K [3,3]); arguments as `rasterize`.
    Gradients flow from the splats back to every input. Arguments are checked as `rasterize` checks them."""
    checked_call(OUTPUTS, ("rgb",), means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree,
                 features, None, near, far, None, True, 0.0, DEFAULT_ALPHA_MIN, DEFAULT_TRANSMITTANCE_MIN, scale_dims=3)
    n = means.shape[0]
    coeffs = colors if colors.dim() == 3 else colors.reshape(n, 1, 3)
    settings = raster_settings(width, height, near, far, DEFAULT_TILE_SIZE, 0.0, sh_degree, DEFAULT_ALPHA_MIN,
                               DEFAULT_TRANSMITTANCE_MIN)
    with on_torch_stream(means.device):
        means2d, conics, cov2d, depths, rgb, valid = _ProjectFunction.apply(
            settings, means, quats, scales, coeffs, viewmat, _intrinsics_vector(K))
    feats = features if features is not None else means.new_zeros(n, 0)
    return Splats(means2d, conics, cov2d, depths, rgb, valid, opacities, feats)


def blend_splats(splats: Splats, width: int, height: int, *, background: Optional[torch.Tensor] = None,
                 outputs: Sequence[str] = ("rgb", "alpha"), tile_size: Optional[int] = None,
                 alpha_min: float = DEFAULT_ALPHA_MIN,
                 transmittance_min: float = DEFAULT_TRANSMITTANCE_MIN,
                 alpha_max: float = DEFAULT_ALPHA_MAX) -> RenderOutput:
    """Bin and blend splats (from `project_splats`, possibly gathered from several processes) into one image, with
    the outputs of `rasterize`. Invalid rows are dropped first; `out.visible` is over the valid rows."""
    unknown = [o for o in outputs if o not in OUTPUTS]
    if unknown:
        raise ValueError(f"outputs: unknown {unknown}; expected some of {OUTPUTS}")
    check_blend_knobs(0.0, alpha_min, transmittance_min, alpha_max)
    if splats.means2d.dim() != 2 or splats.means2d.shape[1] != 2:
        raise ValueError(f"splats.means2d: expected [N, 2], got {list(splats.means2d.shape)}")
    if not bool(splats.valid.all()):
        splats = splats.select(splats.valid)
    if "features" in outputs and splats.features.shape[1] == 0:
        raise ValueError("outputs: 'features' asked for, but the splats carry no feature columns")
    feats = splats.features if "features" in outputs else splats.features[:, :0]
    settings = raster_settings(width, height, 0.01, 1e10, tile_size or DEFAULT_TILE_SIZE, 0.0, None, alpha_min,
                               transmittance_min, alpha_max)
    wanted = pipeline.Wanted(color="rgb" in outputs, depth="depth" in outputs, inv_depth="inv_depth" in outputs,
                             num_features=feats.shape[1])
    with on_torch_stream(splats.means2d.device):
        color, alpha, zacc, inv, fout, visible = _BlendFunction.apply(
            settings, wanted, splats.means2d, splats.conics, splats.cov2d, splats.depths, splats.colors,
            splats.opacities, feats)
    out = RenderOutput(alpha=alpha if "alpha" in outputs else None, visible=visible)
    return set_image_outputs(out, wanted, color, alpha, zacc, inv, fout, background)
