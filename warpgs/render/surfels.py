"""The torch op `rasterize_surfels`: renders 2D Gaussian surfels (2DGS) with the Warp pipeline; gradients come
from the hand-written blend adjoint and the projection's generated adjoint. Two host paths run the same kernels
(`raster_options(path=...)`): "fast" (`surfels_fast`: workspace, recorded launches) and "legacy" (per-call arrays,
a wp.Tape).

Same conventions and arguments as `rasterize`, with scales [N, 2] (the disk's two axes; the quaternion's
third rotation column is the normal) and the extra outputs normal, median_depth and distortion.
"""
from __future__ import annotations

from typing import Optional, Sequence

import torch
import warp as wp

from warpgs.render import pipeline_surfels as surfel_pipeline
from warpgs.render.pipeline_surfels import IMAGES, image_wanted
from warpgs.render.surfels_fast import FastSurfelsFunction
from warpgs.render.pipeline_gaussians import Settings
from warpgs.render.defaults import (DEFAULT_ALPHA_MAX, DEFAULT_ALPHA_MIN, DEFAULT_TILE_SIZE, DEFAULT_TRANSMITTANCE_MIN,
                                    current_raster_options)
from warpgs.render.gaussians import (RenderOutput, _intrinsics_vector, _stack, _to_wp, _wp_device, _zero_grad,
                                     checked_call, checks_before_render, on_torch_stream, raster_settings,
                                     set_image_outputs)

OUTPUTS = ("rgb", "alpha", "depth", "inv_depth", "normal", "median_depth", "distortion", "features")
# 2DGS measures distortion on NDC depth m = f/(f-n) (1 - n/z) with these fixed planes; the constant part
# cancels in the pairwise differences, leaving m = -(f n / (f - n)) / z.
DISTORTION_NEAR = 0.2
DISTORTION_FAR = 100.0
DISTORTION_SCALE = DISTORTION_FAR * DISTORTION_NEAR / (DISTORTION_FAR - DISTORTION_NEAR)



class _RasterizeSurfelsFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, settings, wanted, means, quats, scales, opacities, coeffs, features, viewmat, intrinsics):
        needs = ctx.needs_input_grad[2:]
        any_grad = any(needs)
        grads = [_zero_grad(t) if need else None
                 for t, need in zip((means, quats, scales, opacities, coeffs, features, viewmat, intrinsics), needs)]
        # Arrays the hand-written blend adjoint writes into always need a grad buffer when anything is learnt.
        if any_grad:
            grads[3] = _zero_grad(opacities) if grads[3] is None else grads[3]
            grads[5] = _zero_grad(features) if grads[5] is None else grads[5]
        w_means = _to_wp(means, wp.vec3, grads[0])
        w_quats = _to_wp(quats, wp.vec4, grads[1])
        w_scales = _to_wp(scales, wp.vec2, grads[2])
        w_opac = _to_wp(opacities, wp.float32, grads[3])
        w_coeffs = _to_wp(coeffs, wp.vec3, grads[4])
        w_feat = _to_wp(features, wp.float32, grads[5])
        w_view = _to_wp(viewmat.reshape(1, 4, 4), wp.mat44, None if grads[6] is None else grads[6].view(1, 4, 4))
        w_intr = _to_wp(intrinsics.reshape(1, 4), wp.vec4, None if grads[7] is None else grads[7].view(1, 4))

        tape = wp.Tape()
        with tape:
            proj = surfel_pipeline.project_surfels(w_means, w_quats, w_scales, w_coeffs, w_view, w_intr, settings,
                                                   requires_grad=any_grad)
        bins = surfel_pipeline.bin_surfels(proj, w_opac, settings)
        fwd = surfel_pipeline.blend_forward(proj, bins, w_opac, w_feat, settings, wanted)

        H, W = settings.height, settings.width
        empty = means.new_zeros(0)
        images = [wp.to_torch(getattr(fwd, name)).view(H, W, c) if image_wanted(wanted, name) else empty
                  for name, c, _ in IMAGES]
        feats = wp.to_torch(fwd.features).view(H, W, -1) if wanted.num_features else empty
        visible = wp.to_torch(bins.counts) > 0
        count = torch.tensor(bins.num_intersections)
        ctx.mark_non_differentiable(visible, count)
        ctx.state = (tape, proj, bins, fwd, w_opac, w_feat, settings, wanted, grads)
        ctx.device = means.device
        return tuple(images) + (feats, visible, count)

    @staticmethod
    def backward(ctx, *upstream):
        tape, proj, bins, fwd, w_opac, w_feat, settings, wanted, grads = ctx.state
        npix = settings.width * settings.height
        device = ctx.device
        with on_torch_stream(device):
            g = {}
            for (name, c, dtype), up in zip(IMAGES, upstream):
                if not image_wanted(wanted, name):  # outputs that were not computed: a dummy the kernel never reads
                    g[name] = wp.zeros(1, dtype=dtype)
                    continue
                t = torch.zeros((npix, c), device=device) if up is None else up.contiguous().view(npix, c)
                g[name] = wp.from_torch(t.contiguous() if c == 3 else t.view(npix), dtype=dtype)
            nf = wanted.num_features
            up_f = upstream[len(IMAGES)]
            if nf:
                t = torch.zeros((npix, nf), device=device) if up_f is None else up_f.contiguous().view(npix, nf)
                g["features"] = wp.from_torch(t)
            else:
                g["features"] = wp.zeros((1, 1), dtype=wp.float32)

            def blend_adjoint():
                surfel_pipeline.blend_backward(proj, bins, w_opac, w_feat, settings, wanted, fwd, g)

            tape.record_func(blend_adjoint, [proj.transforms, proj.means2d, proj.depths, proj.colors, proj.normals,
                                             w_opac, w_feat])
            tape.backward()
        ctx.state = None
        return (None, None) + tuple(grads)


def rasterize_surfels(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    *,
    sh_degree: Optional[int] = None,
    features: Optional[torch.Tensor] = None,
    background: Optional[torch.Tensor] = None,
    outputs: Sequence[str] = ("rgb", "alpha"),
    near: float = 0.01,
    far: float = 1e10,
    tile_size: Optional[int] = None,
    max_sigmas: float = 0.0,
    alpha_min: float = DEFAULT_ALPHA_MIN,
    transmittance_min: float = DEFAULT_TRANSMITTANCE_MIN,
    alpha_max: float = DEFAULT_ALPHA_MAX,
    check_inputs: bool = True,
    _pipeline_checks: bool = False,
) -> RenderOutput:
    """Render N 2D Gaussian surfels from one camera (viewmat [4,4], K [3,3]) or a batch ([B,4,4], [B,3,3]).

    scales: [N,2] linear disk scales; the quaternion's rotation has the disk axes as its first two columns
    and the normal as its third. colors/sh_degree/features/background as in `rasterize`.
    outputs: any of rgb, alpha, depth (Σ w z / alpha, z the ray-surfel hit depth), inv_depth (Σ w / z),
    normal (Σ w n, world space, each normal facing the camera), median_depth, distortion, features.
    Only the requested outputs are computed. tile_size, max_sigmas / alpha_min / transmittance_min / alpha_max:
    as in `rasterize`.
    """
    outputs, tile_size = checked_call(OUTPUTS, outputs, means, quats, scales, opacities, colors, viewmat, K, width,
                                      height, sh_degree, features, background, near, far, tile_size, False,
                                      max_sigmas, alpha_min, transmittance_min, scale_dims=2, alpha_max=alpha_max)
    options = current_raster_options()
    pipeline_checks = checks_before_render(check_inputs, _pipeline_checks, means, quats, scales, opacities, colors,
                                           features, viewmat, K, background, options)
    if viewmat.dim() == 3:
        per_camera = [rasterize_surfels(means, quats, scales, opacities, colors, viewmat[b], K[b], width, height,
                                        sh_degree=sh_degree, features=features, background=background,
                                        outputs=outputs, near=near, far=far, tile_size=tile_size,
                                        max_sigmas=max_sigmas, alpha_min=alpha_min,
                                        transmittance_min=transmittance_min, alpha_max=alpha_max,
                                        check_inputs=False, _pipeline_checks=pipeline_checks)
                      for b in range(viewmat.shape[0])]
        return _stack(per_camera)

    n = means.shape[0]
    coeffs = colors if colors.dim() == 3 else colors.reshape(n, 1, 3)
    feats = features if (features is not None and "features" in outputs) else means.new_empty(n, 0)
    settings = raster_settings(width, height, near, far, tile_size, max_sigmas, sh_degree, alpha_min, transmittance_min,
                               alpha_max)
    wanted = surfel_pipeline.SurfelWanted(
        color="rgb" in outputs, depth="depth" in outputs, inv_depth="inv_depth" in outputs,
        normal="normal" in outputs, median="median_depth" in outputs, distortion="distortion" in outputs,
        num_features=feats.shape[1], distortion_scale=DISTORTION_SCALE)
    device = means.device
    fast = options.path == "fast" and n > 0
    if fast:  # returns the expected depth itself (the division runs in a kernel)
        color, alpha, zacc, inv, normal, median, distortion, fout, visible, count = FastSurfelsFunction.apply(
            settings, wanted, options, means, quats, scales, opacities, coeffs, feats, viewmat, _intrinsics_vector(K),
            (features, K, background) if pipeline_checks else None)
    else:
        with on_torch_stream(device):
            color, alpha, zacc, inv, normal, median, distortion, fout, visible, count = \
                _RasterizeSurfelsFunction.apply(settings, wanted, means, quats, scales, opacities, coeffs, feats,
                                                viewmat, _intrinsics_vector(K))
    out = RenderOutput(alpha=alpha if "alpha" in outputs else None, visible=visible, num_intersections=int(count))
    set_image_outputs(out, wanted, color, alpha, zacc, inv, fout, background, depth_normalized=fast)
    if wanted.normal:
        out.normal = normal
    if wanted.median:
        out.median_depth = median
    if wanted.distortion:
        out.distortion = distortion
    return out


def surfel_work(means, quats, scales, opacities, viewmat, K, width: int, height: int, *, near: float = 0.01,
                far: float = 1e10, tile_size: int = DEFAULT_TILE_SIZE) -> dict:
    """For benchmarks: the work one forward pass does on a single camera (no autograd, colour only).

    Returns {"evaluations": surfel-pixel evaluations the blending loops perform (each pixel walks its tile's
    list up to its stopping point), "tile_pairs": surfel-tile pairs after binning}.
    """
    n = means.shape[0]
    s = Settings(width=int(width), height=int(height), near=float(near), far=float(far), tile_size=int(tile_size))
    want = surfel_pipeline.SurfelWanted(color=False, depth=False, inv_depth=False, normal=False, median=False,
                                        distortion=False, num_features=0, distortion_scale=DISTORTION_SCALE)
    with wp.ScopedDevice(_wp_device(means.device)):
        opac = _to_wp(opacities, wp.float32)
        proj = surfel_pipeline.project_surfels(
            _to_wp(means, wp.vec3), _to_wp(quats, wp.vec4), _to_wp(scales, wp.vec2),
            _to_wp(means.new_zeros(n, 1, 3), wp.vec3), _to_wp(viewmat.reshape(1, 4, 4), wp.mat44),
            _to_wp(_intrinsics_vector(K).reshape(1, 4), wp.vec4), s, requires_grad=False)
        bins = surfel_pipeline.bin_surfels(proj, opac, s)
        fwd = surfel_pipeline.blend_forward(proj, bins, opac, wp.zeros((1, 1), dtype=wp.float32), s, want)
        last = wp.to_torch(fwd.last).view(s.height, s.width).long()
        start = wp.to_torch(bins.tile_start).long()
    ty = torch.arange(s.height, device=last.device) // s.tile_size
    tx = torch.arange(s.width, device=last.device) // s.tile_size
    walked = (last - start[ty[:, None] * s.tiles_x + tx[None, :]]).clamp_min(0)
    return {"evaluations": int(walked.sum().item()), "tile_pairs": bins.num_intersections}
