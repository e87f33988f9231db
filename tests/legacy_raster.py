"""The per-call 3D op the fast one (render/gaussians_fast.py) replaced, kept as the tests' oracle: the same kernels
driven the simple way (`warpgs.render.pipeline_gaussians`: per-call arrays, a wp.Tape for the projection's adjoint,
the blend adjoint recorded on it), so on the CPU the fast path must give the same images to the last bit and the
same gradients (bit for bit, or to float rounding where it sums in another order). `rasterize_legacy` takes the
arguments of `rasterize` that the tests use."""
from __future__ import annotations

from contextlib import nullcontext

import torch
import warp as wp

from warpgs.render import pipeline_gaussians as pipeline
from warpgs.render.defaults import DEFAULT_ALPHA_MAX, DEFAULT_ALPHA_MIN, DEFAULT_TRANSMITTANCE_MIN, choose_tile_size
from warpgs.render.gaussians import (RenderOutput, _intrinsics_vector, _stack, _to_wp, _zero_grad, blended_images,
                                     op_inputs, raster_settings, set_image_outputs, upstream_image_gradients)
from warpgs.render.torch_streams import on_torch_stream


def warp_inputs(tensors, needs, any_grad: bool, scale_dtype):
    """(gradient buffers, Warp arrays) of an op's (means, quats, scales, opacities, coeffs, features, viewmat,
    intrinsics): a zeroed buffer where `needs`, and for opacities and features whenever anything is learnt (the
    hand-written blend adjoint writes into them)."""
    grads = [_zero_grad(t) if need else None for t, need in zip(tensors, needs)]
    if any_grad:
        for i in (3, 5):
            grads[i] = _zero_grad(tensors[i]) if grads[i] is None else grads[i]
    means, quats, scales, opacities, coeffs, features, viewmat, intrinsics = tensors
    arrays = [_to_wp(means, wp.vec3, grads[0]), _to_wp(quats, wp.vec4, grads[1]),
              _to_wp(scales, scale_dtype, grads[2]), _to_wp(opacities, wp.float32, grads[3]),
              _to_wp(coeffs, wp.vec3, grads[4]), _to_wp(features, wp.float32, grads[5]),
              _to_wp(viewmat.reshape(1, 4, 4), wp.mat44, None if grads[6] is None else grads[6].view(1, 4, 4)),
              _to_wp(intrinsics.reshape(1, 4), wp.vec4, None if grads[7] is None else grads[7].view(1, 4))]
    return grads, arrays


class _RasterizeFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, settings, wanted, means, quats, scales, opacities, coeffs, features, viewmat, intrinsics,
                means2d_probe):
        needs = ctx.needs_input_grad[2:10]
        any_grad = any(ctx.needs_input_grad[2:])  # the means2d probe alone also needs the blend adjoint
        grads, (w_means, w_quats, w_scales, w_opac, w_coeffs, w_feat, w_view, w_intr) = warp_inputs(
            (means, quats, scales, opacities, coeffs, features, viewmat, intrinsics), needs, any_grad, wp.vec3)

        tape = wp.Tape()
        # With geometry and colour frozen (e.g. training only opacities or features) the projection's
        # adjoint has nothing to deliver: leave it off the tape.
        project_grad = any(needs[i] for i in (0, 1, 2, 4, 6, 7))
        with tape if project_grad else nullcontext():
            proj = pipeline.project_gaussians(w_means, w_quats, w_scales, w_opac, w_coeffs, w_view, w_intr,
                                              settings, requires_grad=any_grad)
        bins = pipeline.bin_gaussians(proj, w_opac, settings)
        fwd = pipeline.blend_forward(proj, bins, w_opac, w_feat, settings, wanted)

        color, alpha, depth, inv_depth, feats = blended_images(fwd, settings, wanted)
        visible = wp.to_torch(bins.counts) > 0
        if means2d_probe is not None:  # gives the probe the projected centres; its grad is dL/dmeans2d
            means2d_probe.data.copy_(wp.to_torch(proj.means2d).view(-1, 2))
        ctx.state = (tape, proj, bins, fwd, w_opac, w_feat, settings, wanted, grads)
        empty = means.new_zeros(0)
        outs = [color, alpha, depth, inv_depth, feats]
        count = torch.tensor(bins.num_intersections)
        ctx.mark_non_differentiable(visible, count)
        ctx.device = means.device
        return tuple(empty if o is None else o for o in outs) + (visible, count)

    @staticmethod
    def backward(ctx, g_color, g_alpha, g_depth, g_inv, g_feat, _g_visible, _g_count):
        tape, proj, bins, fwd, w_opac, w_feat, settings, wanted, grads = ctx.state
        device = ctx.device
        if proj.means2d.shape[0] == 0:  # empty scene: nothing to differentiate (Warp has no grads for size 0)
            ctx.state = None
            probe_grad = torch.zeros(0, 2, device=device) if ctx.needs_input_grad[10] else None
            return (None, None) + tuple(grads) + (probe_grad,)

        with on_torch_stream(device):
            gc, ga, gd, gi, gf = upstream_image_gradients(g_color, g_alpha, g_depth, g_inv, g_feat, settings, wanted,
                                                          device)

            g2d = []

            def blend_adjoint():
                pipeline.blend_backward(proj, bins, w_opac, w_feat, settings, wanted, fwd, gc, ga, gd, gi, gf)
                if ctx.needs_input_grad[10]:  # read before the projection adjoint consumes it
                    g2d.append(wp.to_torch(proj.means2d.grad).view(-1, 2).clone())

            tape.record_func(blend_adjoint, [proj.means2d, proj.conics, proj.colors, proj.depths, w_opac, w_feat])
            tape.backward()
        ctx.state = None
        return (None, None) + tuple(grads) + (g2d[0] if g2d else None,)


def rasterize_legacy(means, quats, scales, opacities, colors, viewmat, K, width, height, *, sh_degree=None,
                     features=None, background=None, outputs=("rgb", "alpha"), tile_size=None,
                     track_means2d=False, _means2d_probe=None) -> RenderOutput:
    """`rasterize` (default thresholds, inputs unchecked) through the per-call op."""
    kw = dict(sh_degree=sh_degree, features=features, background=background, outputs=outputs)
    grad = torch.is_grad_enabled() and any(t is not None and t.requires_grad
                                           for t in (means, quats, scales, opacities, colors, features))
    tile_size = choose_tile_size(tile_size, grad or track_means2d, on_gpu=means.device.type == "cuda")
    if viewmat.dim() == 3:
        probe = means.new_zeros(viewmat.shape[0], means.shape[0], 2, requires_grad=True) if track_means2d else None
        out = _stack([rasterize_legacy(means, quats, scales, opacities, colors, viewmat[b], K[b], width, height,
                                       tile_size=tile_size, _means2d_probe=None if probe is None else probe[b], **kw)
                      for b in range(viewmat.shape[0])])
        out.means2d = probe
        return out
    probe = _means2d_probe
    if probe is None and track_means2d:
        probe = means.new_zeros(means.shape[0], 2, requires_grad=True)
    coeffs, feats = op_inputs(means, colors, features, outputs)
    settings = raster_settings(width, height, 0.01, 1e10, tile_size, 0.0, sh_degree, DEFAULT_ALPHA_MIN,
                               DEFAULT_TRANSMITTANCE_MIN, DEFAULT_ALPHA_MAX)
    wanted = pipeline.Wanted(color="rgb" in outputs, depth="depth" in outputs, inv_depth="inv_depth" in outputs,
                             num_features=feats.shape[1])
    with on_torch_stream(means.device):
        color, alpha, zacc, inv, fout, visible, count = _RasterizeFunction.apply(
            settings, wanted, means, quats, scales, opacities, coeffs, feats, viewmat, _intrinsics_vector(K), probe)
    out = RenderOutput(alpha=alpha if "alpha" in outputs else None, visible=visible, num_intersections=int(count),
                       means2d=probe)
    return set_image_outputs(out, wanted, color, alpha, zacc, inv, fout, background)
