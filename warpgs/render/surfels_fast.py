"""The torch side of the lean surfel path (`fast_pipeline_surfels`), with the lifetimes of the 3D one
(`gaussians_fast`): tensors cross as bare array descriptors, outputs are fresh torch tensors, and what the backward
reads lives in a buffer set lent to the render for exactly as long as its autograd graph."""
from __future__ import annotations

import torch
import warp as wp

from warpgs.render import fast_pipeline_surfels as fast
from warpgs.render.differentiable_once import differentiable_once
from warpgs.render.fast_pipeline_surfels import IMAGES, image_wanted
from warpgs.render.fast_pipeline import feature_layout
from warpgs.render.gradient_block import FEATURES, OPACITIES, GradientBlock
from warpgs.render.device_state import backward_state, device_state
from warpgs.render.gaussians_fast import (_features_arg, detached_inputs, feature_gradient_at, input_check,
                                          overflow_flag, projection_adjoint,
                                          projection_inputs, staged_camera, take_backward_state,
                                          upstream_features, upstream_gradient)

ALPHA, DEPTH = (next(i for i, (name, _, _) in enumerate(IMAGES) if name == n) for n in ("alpha", "depth"))


class FastSurfelsFunction(torch.autograd.Function):
    """The surfel op through `fast_pipeline_surfels` (tests/legacy_raster_surfels.py holds a per-call op it must
    match bit for bit); `check` as in gaussians_fast.FastRasterizeFunction."""

    @staticmethod
    def forward(ctx, settings, wanted, options, means, quats, scales, opacities, coeffs, features, viewmat,
                intrinsics, check=None):
        needs = ctx.needs_input_grad[3:11]
        any_grad = any(needs)
        state = device_state(means.device)
        ws = state.ws
        H, W = settings.height, settings.width
        npix = H * W
        nf = wanted.num_features
        layout = feature_layout(state.wdev)
        (means, quats, scales, opacities, coeffs, features), viewmat, intrinsics = detached_inputs(
            ctx, (means, quats, scales, opacities, coeffs, features), viewmat, intrinsics)
        desc = state.desc
        view, intr, check = staged_camera(state, viewmat, intrinsics, check)
        inputs = projection_inputs(state, (means, quats, scales, coeffs, view, intr), wp.vec2)

        empty = means.new_empty(0)
        images = [means.new_empty(H, W, c) if image_wanted(wanted, name) else empty for name, c, _ in IMAGES]
        # the per-thread CPU kernels accumulate features in place; the cooperative ones write every pixel
        feats = ((means.new_zeros if layout == "rows" else means.new_empty)(H, W, nf)) if nf else empty
        outputs = [desc(img.view(npix, c) if c > 1 else img.view(npix), dtype) if image_wanted(wanted, name)
                   else ws.dummy(dtype) for img, (name, c, dtype) in zip(images, IMAGES)]
        outputs.append(_features_arg(feats.view(npix, nf), nf, layout, state))
        keep = ws.lease_frame() if any_grad else None  # back to the pool with ctx.state
        # the blend accumulates depth in `zacc` (the adjoint reads it) and writes the depth image, zacc over alpha,
        # beside it
        outputs.append(outputs[DEPTH])
        zacc = ws.dummy(float)
        if wanted.depth:
            zacc = outputs[DEPTH] = (keep if keep is not None else ws)("zacc", npix, float)

        alive = []
        checks = None if check is None else input_check(state, (means, quats, scales, opacities, coeffs), view,
                                                        check, alive)
        overflowed, overflow = overflow_flag(state, options, means)
        with state.scope():
            frame = fast.forward(ws, settings, wanted, inputs, desc(opacities, wp.float32),
                                 _features_arg(features, nf, layout, state), outputs, keep, checks,
                                 options.deterministic, overflow)
            visible = state.tensor(frame.counts) > 0
        count = frame.total  # a plain int (-1: not read, speculative): autograd passes it through
        ctx.mark_non_differentiable(visible)
        if overflowed is not None:
            ctx.mark_non_differentiable(overflowed)
        if any_grad:
            ctx.state = (frame, keep, zacc, settings, wanted, options, needs, layout)
            ctx.save_for_backward(means, quats, scales, opacities, coeffs, features, viewmat, intrinsics)
            ctx.forward_state = state
        return tuple(images) + (feats, visible, count, overflowed)

    @staticmethod
    @differentiable_once("the surfel render (rasterize_surfels)")
    def backward(ctx, *upstream):  # the images', then features', visible's, count's and the overflow flag's
        frame, keep, zacc, settings, wanted, options, needs, layout = take_backward_state(ctx)
        saved = ctx.saved_tensors  # unpacked once: each read of ctx.saved_tensors unpacks them again
        means, quats, scales, opacities, coeffs, features, viewmat, intrinsics = saved
        state = backward_state(ctx.forward_state)
        ws = state.ws
        npix = settings.width * settings.height
        nf = wanted.num_features

        # the blend adjoint is launched before the gradients' torch views are made: the GPU waits for that launch
        gradients = GradientBlock(saved, ctx.camera_shapes, needs)

        alive = []  # descriptors hold no reference: contiguous copies must outlive the launches
        ups = [upstream_gradient(state, layout, alive, g, f"up_{name}", (npix, c) if c > 1 else (npix,), dtype)
               if image_wanted(wanted, name) else ws.dummy(dtype)
               for g, (name, c, dtype) in zip(upstream, IMAGES)]
        ups.append(upstream_features(state, layout, alive, upstream[len(IMAGES)], npix, nf))
        desc = state.desc
        with state.scope():
            projected = fast.blend_backward(ws, frame, settings, wanted, desc(opacities, wp.float32),
                                            _features_arg(features, nf, layout, state), ups,
                                            state.array_at(gradients.address(OPACITIES), opacities.shape[0],
                                                           wp.float32),
                                            feature_gradient_at(gradients.address(FEATURES), features.shape[0], nf,
                                                                layout, state),
                                            features.shape[0], options.surfel_backward_kernel, zacc=zacc)
            grads, g_opac, g_features = gradients.views()
            if any(needs[i] for i in (0, 1, 2, 4, 6, 7)):
                projection_adjoint(state, fast.project_backward, frame, settings,
                                   (means, quats, scales, coeffs, viewmat, intrinsics), grads, needs, projected,
                                   wp.vec2)
        grads[3] = g_opac if needs[3] else None
        grads[5] = g_features if needs[5] else None
        return (None, None, None) + tuple(grads) + (None,)
