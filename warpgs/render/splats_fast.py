"""The two torch ops of the render cut at the projected splats (`render/splats.py`), over the lean pipeline the whole
3D op uses (`fast_pipeline`): the projection kernel and its generated adjoint, and the binning, sort, blend and the
hand-written blend adjoints (per-warp sums on GPUs) with buffers reused across calls. Model-parallel training renders
through these, so a sharded render costs what a whole one does, plus the exchange.

Lifetimes are those of `gaussians_fast`: the blend's backward reads buffers lent to the render for as long as its
autograd context lives; the outputs and the gradients handed back are fresh tensors."""
from __future__ import annotations

import torch
import warp as wp

from warpgs.kernels import project
from warpgs.render import fast_pipeline as fast
from warpgs.render.defaults import DEPTH_EPS
from warpgs.render.gaussians_fast import (_features_arg, device_state, feature_gradient_arg, image_outputs,
                                          projection_inputs, upstream_features, upstream_gradient)

_PROJECTED = (("means2d", wp.vec2, 2), ("conics", wp.vec3, 3), ("cov2d", wp.vec3, 3), ("depths", wp.float32, 0),
              ("colors", wp.vec3, 3), ("valid", wp.int32, 0))  # the projection's outputs: name, dtype, columns


class FastProjectFunction(torch.autograd.Function):
    """apply(settings, means, quats, scales, coeffs, viewmat [4,4], intrinsics [4]) -> (means2d, conics, cov2d,
    depths, colors, valid) of every primitive; cov2d and valid carry no gradient."""

    @staticmethod
    def forward(ctx, settings, means, quats, scales, coeffs, viewmat, intrinsics):
        state = device_state(means.device)
        n = means.shape[0]
        tensors = [t.contiguous() for t in (means, quats, scales, coeffs)]
        camera = [viewmat.reshape(1, 4, 4).contiguous(), intrinsics.reshape(1, 4).contiguous()]
        outs = [torch.empty((n, cols) if cols else (n,), device=means.device,
                            dtype=torch.int32 if name == "valid" else torch.float32) for name, _, cols in _PROJECTED]
        inputs = projection_inputs(state, tensors + camera, wp.vec3)
        with state.scope():
            state.ws.launches.launch("split_project", project.project_gaussians, n, fast.projection_args(
                settings, inputs, [state.desc(t, dtype) for t, (_, dtype, _) in zip(outs, _PROJECTED)]))
        valid = outs[5] > 0
        ctx.mark_non_differentiable(outs[2], valid)
        ctx.save_for_backward(*tensors, *camera)
        ctx.settings, ctx.camera_shapes = settings, (viewmat.shape, intrinsics.shape)
        return outs[0], outs[1], outs[2], outs[3], outs[4], valid

    @staticmethod
    def backward(ctx, g_means2d, g_conics, _g_cov2d, g_depths, g_colors, _g_valid):
        saved = ctx.saved_tensors
        needs = ctx.needs_input_grad[1:7]
        n = saved[0].shape[0]
        grads = [torch.zeros_like(t) if need else None for t, need in zip(saved, needs)]
        if n and any(needs):
            state = device_state(saved[0].device)
            ws = state.ws
            alive = []  # descriptors hold no reference: contiguous copies must outlive the launch
            upstream = [upstream_gradient(state, "vectors", alive, g, f"split_up_{name}", (n, cols) if cols else (n,),
                                          dtype)
                        for g, (name, dtype, cols) in zip((g_means2d, g_conics, g_colors, g_depths),
                                                          (_PROJECTED[0], _PROJECTED[1], _PROJECTED[4], _PROJECTED[3]))]
            scratch = [ws.array(f"split_replay_{name}", n, dtype) for name, dtype, _ in _PROJECTED]
            dtypes = (wp.vec3, wp.vec4, wp.vec3, wp.vec3, wp.mat44, wp.vec4)
            input_grads = [None if g is None else state.desc(g, dt) for g, dt in zip(grads, dtypes)]
            with state.scope():
                fast.launch_projection_adjoint(ws, "split_project_adjoint", ctx.settings, n,
                                               projection_inputs(state, list(saved), wp.vec3), scratch, input_grads,
                                               upstream)
        view_shape, intr_shape = ctx.camera_shapes
        if grads[4] is not None:
            grads[4] = grads[4].view(view_shape)
        if grads[5] is not None:
            grads[5] = grads[5].view(intr_shape)
        return (None,) + tuple(grads)


class FastBlendFunction(torch.autograd.Function):
    """apply(settings, wanted, deterministic, means2d, conics, cov2d, depths, colors, opacities, features) ->
    (color, alpha, depth, inv_depth, features, visible) of n >= 1 valid splats, as the whole op's blend gives them
    (depth already divided by alpha; empty tensors for outputs not wanted)."""

    @staticmethod
    def forward(ctx, settings, wanted, deterministic, means2d, conics, cov2d, depths, colors, opacities, features):
        any_grad = any(ctx.needs_input_grad[3:])
        state = device_state(means2d.device)
        ws, desc = state.ws, state.desc
        npix, nf, n = settings.width * settings.height, wanted.num_features, means2d.shape[0]
        layout = fast.feature_layout(state.wdev)
        means2d, conics, cov2d, depths, colors, opacities, features = (
            t.contiguous() for t in (means2d, conics, cov2d, depths, colors, opacities, features))
        valid = ws.array("split_valid", n, wp.int32)
        projected = (desc(means2d, wp.vec2), desc(conics, wp.vec3), desc(cov2d, wp.vec3), desc(depths, wp.float32),
                     desc(colors, wp.vec3), valid)
        keep = ws.lease_frame() if any_grad else None
        (color, alpha, depth, inv_depth, feats), zacc, outputs = image_outputs(state, means2d, settings, wanted,
                                                                               layout, keep)
        with state.scope():
            valid.fill_(1)  # every splat handed in is valid (render/splats.py drops the others first)
            frame = fast.bin_and_blend(ws, settings, wanted, projected, desc(opacities, wp.float32),
                                       _features_arg(features, nf, layout, state), outputs, keep,
                                       deterministic=deterministic)
            if wanted.depth:
                fast.normalize_depth(ws, zacc, outputs[1], desc(depth.view(npix), wp.float32), npix, DEPTH_EPS)
            visible = state.tensor(frame.counts) > 0
        ctx.mark_non_differentiable(visible)
        if any_grad:
            ctx.state = (frame, keep, zacc, settings, wanted, layout)
            ctx.save_for_backward(means2d, conics, depths, colors, opacities, features)  # what the frame points at
        return color, alpha, depth, inv_depth, feats, visible

    @staticmethod
    def backward(ctx, g_color, g_alpha, g_depth, g_inv, g_feat, _g_visible):
        frame, keep, zacc, settings, wanted, layout = ctx.state
        ctx.state = None
        means2d, _conics, _depths, _colors, opacities, features = ctx.saved_tensors
        state = device_state(means2d.device)
        ws, n, nf = state.ws, frame.n, wanted.num_features
        npix = settings.width * settings.height
        g_opacities = torch.zeros_like(opacities)
        g_features = torch.zeros_like(features)
        alive = []

        def upstream(g, name, shape, dtype):
            return upstream_gradient(state, layout, alive, g, name, shape, dtype)

        gc = upstream(g_color, "up_color", (npix, 3), wp.vec3) if wanted.color else ws.dummy(wp.vec3)
        ga = upstream(g_alpha, "up_alpha", (npix,), wp.float32)
        gd = upstream(g_depth, "up_depth", (npix,), wp.float32) if wanted.depth else ws.dummy(float)
        gi = upstream(g_inv, "up_inv_depth", (npix,), wp.float32) if wanted.inv_depth else ws.dummy(float)
        gf = upstream_features(state, layout, alive, g_feat, npix, nf)
        with state.scope():
            if wanted.depth and g_depth is not None:  # through the division by alpha first
                gd, ga = fast.normalize_depth_backward(ws, gd, zacc, frame.transmittance,
                                                       None if g_alpha is None else ga, npix, DEPTH_EPS)
            projected = fast.blend_backward(
                ws, frame, settings, wanted, state.desc(opacities, wp.float32),
                _features_arg(features, nf, layout, state), (gc, ga, gd, gi, gf),
                state.array(g_opacities, n, wp.float32), feature_gradient_arg(g_features, nf, layout, state), n)
            g_means2d, g_conics, g_colors, g_depths = (state.tensor(a).reshape(shape).clone() for a, shape in
                                                       zip(projected, ((n, 2), (n, 3), (n, 3), (n,))))
        return (None, None, None, g_means2d, g_conics, None, g_depths, g_colors, g_opacities,
                g_features if nf else None)
