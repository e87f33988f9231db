"""The torch side of the lean 3D path (`fast_pipeline`): tensors cross as bare array descriptors; what a backward
reads lives in buffers lent to the render (`Workspace.lease_frame`) for exactly as long as its autograd graph.

Lifetimes, which is what makes reusing scratch memory safe:
- outputs returned to the caller are fresh torch tensors; everything the backward reads (projected Gaussians,
  footprint cut-offs, tile ranges, sorted ids, final transmittance and stopping index) is in a leased buffer set
  when autograd will differentiate the render; `ctx` holds the lease until the backward has run (or the graph is
  freed), and only then can another render get that set;
- the workspace (`warpgs.render.workspace`) holds only what a call uses and forgets before it returns (sort keys,
  prefix sums, tile rectangles, the visible counts, the projected gradients of one backward), per thread and stream.
So two renders in flight (two forwards, then their backwards in any order) share no buffer a backward reads
(tests/test_raster_fast_path.py checks it).
"""
from __future__ import annotations

import torch
import warp as wp

from warpgs.render import fast_pipeline as fast
from warpgs.render.camera_rows import camera_rows
from warpgs.render.device_state import DeviceState, backward_state, device_state
from warpgs.render.differentiable_once import differentiable_once
from warpgs.render.gradient_block import FEATURES, OPACITIES, GradientBlock
from warpgs.render.pipeline_gaussians import _cooperative
from warpgs.render.validation import raise_flagged


def _features_arg(t, num_features: int, layout: str, state: "DeviceState"):
    """Features (or their gradients) for the blend kernels: [rows, C] floats on the CPU, length-C vectors on GPUs."""
    if num_features == 0:
        ws = state.ws
        return ws.dummy(float, 2) if layout == "rows" else ws.dummy(fast.blend_gpu.feature_vector_type(0))
    if layout == "rows":
        return state.desc(t, wp.float32)
    return state.desc(t, fast.blend_gpu.feature_vector_type(num_features))


def detached_inputs(ctx, primitives, viewmat: torch.Tensor, intrinsics: torch.Tensor):
    """(primitives, viewmat, intrinsics) as the fast ops hand them to Warp: the per-primitive tensors (means, quats,
    scales, opacities, coeffs, features) contiguous, the camera as [1, 4, 4] and [1, 4]. Records the camera's
    shapes (ctx.camera_shapes) for its gradients, and tells autograd not to materialise zero gradients for outputs
    the loss did not use (the backward takes None there). No detach: inside an autograd.Function's forward the
    inputs record nothing, and each detach is a dispatch (host time is most of a 100k-primitive GPU render)."""
    ctx.camera_shapes = (viewmat.shape, intrinsics.shape)
    ctx.set_materialize_grads(False)
    return ([t if t.is_contiguous() else t.contiguous() for t in primitives],
            viewmat.reshape(1, 4, 4).contiguous(), intrinsics.reshape(1, 4).contiguous())


def take_backward_state(ctx) -> tuple:
    """The state a render's forward left for its backward, taken: the buffer set it holds goes back to the pool when
    the backward returns (held to the graph's end, a caller keeping each step's loss would lease a set a step)."""
    state = ctx.state
    if state is None:
        raise RuntimeError("render backward: this render was back-propagated already (retain_graph=True); the render "
                           "ops give their buffers back after one backward: render again, or sum the losses into "
                           "one backward")
    ctx.state = None
    return state


class _NoAutogradContext:
    """What a fast op's forward uses of its autograd context, for a call autograd will not differentiate."""

    def __init__(self, num_args: int):
        self.needs_input_grad = (False,) * num_args

    def set_materialize_grads(self, value: bool) -> None:
        pass

    def mark_non_differentiable(self, *tensors) -> None:
        pass


def run_op(function, *args):
    """function.apply(*args), or its forward alone when autograd will not differentiate the call (grad mode off,
    or no tensor argument needs a gradient: evaluation, viewers): the outputs are the same tensors, without the
    Function's bookkeeping, a noticeable part of a small render's fixed cost."""
    if torch.is_grad_enabled():
        for a in args:
            if isinstance(a, torch.Tensor) and a.requires_grad:
                return function.apply(*args)
    return function.forward(_NoAutogradContext(len(args)), *args)


_PROJECTION_DTYPES = (wp.vec3, wp.vec4, None, wp.vec3, wp.mat44, wp.vec4)  # scales: vec3 or vec2 (surfels)
_CAMERA_VIEWS = (None, None, None, None, (1, 4, 4), (1, 4))


def overflow_flag(state: "DeviceState", options, like: torch.Tensor) -> tuple:
    """(overflowed, overflow) for a render with the speculative_pairs option: the 0-d int32 tensor the render sets to 1
    when its pairs did not fit the room sized from earlier calls (pair_room.py; zeroed here when deterministic: that
    path sizes exactly and never writes it) and its array for the pipeline; (None, None) without the option."""
    if not options.speculative_pairs:
        return None, None
    overflowed = (like.new_zeros if options.deterministic else like.new_empty)((), dtype=torch.int32)
    return overflowed, state.desc(overflowed.view(1), wp.int32)


def projection_inputs(state: "DeviceState", tensors, scale_dtype) -> list:
    """Descriptors of (means, quats, scales, coeffs, viewmat [1,4,4], intrinsics [1,4]), contiguous tensors, as the
    projection kernels take them."""
    return [state.desc(t, scale_dtype if dt is None else dt) for t, dt in zip(tensors, _PROJECTION_DTYPES)]


def projection_gradients(state: "DeviceState", grads, scale_dtype) -> list:
    """The projection adjoint's gradient descriptors from the op's eight input gradients (means, quats, scales,
    opacities, coeffs, features, viewmat, intrinsics; None where not wanted): those of the projection inputs."""
    picked = (grads[0], grads[1], grads[2], grads[4], grads[6], grads[7])
    return [None if g is None else state.desc(g if v is None else g.view(v), scale_dtype if dt is None else dt)
            for g, dt, v in zip(picked, _PROJECTION_DTYPES, _CAMERA_VIEWS)]


def projection_adjoint(state: "DeviceState", backward, frame, settings, tensors, grads, needs, projected,
                       scale_dtype) -> None:
    """Runs `backward` (a pipeline's project_backward) on the projection inputs `tensors` (means, quats, scales,
    coeffs, viewmat, intrinsics) with the op's eight input gradients. On GPUs (the cooperative kernels) a wanted
    camera gradient goes through one camera row per primitive (camera_rows.py), not atomics that all queue on one
    matrix; CPU threads add without contention and keep the single matrix."""
    means, quats, scales, coeffs, viewmat, intrinsics = tensors
    rows = None
    if (needs[6] or needs[7]) and _cooperative(state.wdev):
        rows = camera_rows(frame.n, viewmat, intrinsics, needs[6], needs[7])
        viewmat, intrinsics = rows.viewmat, rows.intrinsics
    inputs = projection_inputs(state, (means, quats, scales, coeffs, viewmat, intrinsics), scale_dtype)
    input_grads = projection_gradients(state, grads, scale_dtype)
    if rows is not None:
        input_grads[4:] = [None if g is None else state.desc(g, dt)
                           for g, dt in ((rows.g_viewmat, wp.mat44), (rows.g_intrinsics, wp.vec4))]
    backward(state.ws, frame, settings, inputs, input_grads, projected)
    if rows is not None:
        rows.add_into(grads[6], grads[7])


def upstream_gradient(state: "DeviceState", layout: str, alive: list, g, name: str, shape, dtype, rows_dtype=None):
    """The upstream gradient of an output in the kernels' layout (a descriptor of a contiguous copy, appended to
    `alive`, which must outlive the launches); a shared zero buffer when autograd has none (the loss did not use
    that output). rows_dtype: the dtype of the CPU kernels' [rows, C] layout, where it differs."""
    rows = rows_dtype is not None and layout == "rows"
    if g is None:
        return state.ws.zeros(name, shape, float) if rows else state.ws.zeros(name, shape[0], dtype)
    g = g.contiguous().view(shape)
    alive.append(g)
    return state.desc(g, rows_dtype if rows else dtype)


def upstream_features(state: "DeviceState", layout: str, alive: list, g, npix: int, num_features: int):
    """`upstream_gradient` of the feature image (a dummy when no features were rendered)."""
    if not num_features:
        return _features_arg(None, 0, layout, state)
    return upstream_gradient(state, layout, alive, g, "up_features", (npix, num_features),
                             fast.blend_gpu.feature_vector_type(num_features), wp.float32)


def feature_gradient_arg(g_features: torch.Tensor, num_features: int, layout: str, state: "DeviceState"):
    """Where the blend adjoint accumulates the feature gradients ([rows, C] floats on the CPU, vectors on GPUs)."""
    return feature_gradient_at(g_features.data_ptr(), g_features.shape[0], num_features, layout, state)


def feature_gradient_at(address: int, rows: int, num_features: int, layout: str, state: "DeviceState"):
    """`feature_gradient_arg` of [rows, num_features] float32 gradients at a device address."""
    if num_features and layout == "rows":
        return wp.array(ptr=address, dtype=wp.float32, shape=(rows, num_features), device=state.wdev)
    if num_features:
        return state.array_at(address, rows, fast.blend_gpu.feature_vector_type(num_features))
    return _features_arg(None, 0, layout, state)


def blend_upstream(state: "DeviceState", layout: str, alive: list, settings, wanted, grads) -> tuple:
    """The blend adjoint's upstream (color, alpha, depth, inv_depth, features) from the op's output gradients
    `grads` (None where the loss did not use an output; zero buffers there), as the kernels take them: the depth's is
    the expected depth's, which the adjoint takes through the division itself. Copies go to `alive`."""
    g_color, g_alpha, g_depth, g_inv, g_feat = grads
    ws = state.ws
    npix = settings.width * settings.height

    def upstream(g, name, shape, dtype):
        return upstream_gradient(state, layout, alive, g, name, shape, dtype)

    gc = upstream(g_color, "up_color", (npix, 3), wp.vec3) if wanted.color else ws.dummy(wp.vec3)
    ga = upstream(g_alpha, "up_alpha", (npix,), wp.float32)
    gd = upstream(g_depth, "up_depth", (npix,), wp.float32) if wanted.depth else ws.dummy(float)
    gi = upstream(g_inv, "up_inv_depth", (npix,), wp.float32) if wanted.inv_depth else ws.dummy(float)
    gf = upstream_features(state, layout, alive, g_feat, npix, wanted.num_features)
    return gc, ga, gd, gi, gf


def image_outputs(state: "DeviceState", like: torch.Tensor, settings, wanted, layout: str, keep):
    """The blend's outputs for one render: ((color, alpha, depth, inv_depth, features) fresh [H, W, C] tensors on
    `like`'s device, empty where not wanted; zacc, the depth accumulation in `keep` (or the workspace); the arrays
    as the blend kernels take them, `fast.forward`'s `outputs`)."""
    ws, desc = state.ws, state.desc
    H, W = settings.height, settings.width
    npix, nf = H * W, wanted.num_features
    empty = like.new_empty(0)
    color = like.new_empty(H, W, 3) if wanted.color else empty
    alpha = like.new_empty(H, W, 1)
    depth = like.new_empty(H, W, 1) if wanted.depth else empty
    inv_depth = like.new_empty(H, W, 1) if wanted.inv_depth else empty
    # the per-thread CPU kernels accumulate features in place; the cooperative ones write every pixel
    feats = ((like.new_zeros if layout == "rows" else like.new_empty)(H, W, nf)) if nf else empty
    # the blend accumulates depth in `zacc` (the adjoint reads it) and writes `depth`, zacc over alpha, beside it
    zacc = (keep if keep is not None else ws)("zacc", npix, float) if wanted.depth else ws.dummy(float)
    arrays = [desc(color.view(npix, 3), wp.vec3) if wanted.color else ws.dummy(wp.vec3),
              desc(alpha.view(npix), wp.float32), zacc,
              desc(inv_depth.view(npix), wp.float32) if wanted.inv_depth else ws.dummy(float),
              _features_arg(feats.view(npix, nf), nf, layout, state),
              desc(depth.view(npix), wp.float32) if wanted.depth else ws.dummy(float)]
    return (color, alpha, depth, inv_depth, feats), zacc, arrays


def staged_camera(state: "DeviceState", viewmat: torch.Tensor, intrinsics: torch.Tensor, check):
    """(viewmat, intrinsics, check) as the forward's launch sequence reads them: copied, in one copy, into a buffer
    of the state's own (`DeviceState.staged_together`), so the sequence's key does not change with the view. check:
    None, or the caller's (features, K, background), K and background staged too. The backward reads the caller's
    tensors (saved by the op): the buffer is rewritten by the next render."""
    if check is None:
        return tuple(state.staged_together((viewmat, intrinsics))) + (None,)
    features, K, background = check
    if background is None:
        view, intr, K = state.staged_together((viewmat, intrinsics, K))
    else:
        view, intr, K, background = state.staged_together((viewmat, intrinsics, K, background))
    return view, intr, (features, K, background)


def input_check(state: "DeviceState", primitives, viewmat: torch.Tensor, extra, alive: list) -> fast.InputCheck:
    """The finite-value check of a render (fast_pipeline.InputCheck). primitives: the contiguous (means, quats,
    scales, opacities, coeffs); viewmat [1, 4, 4]; extra: the caller's (features or None, K [3, 3], background or
    None), checked as given (features even when not rendered, all nine entries of K). Copies made here go to
    `alive`, which must outlive the render's sync."""
    features, K, background = extra
    tensors = list(primitives) + [features, viewmat, K, background]
    tensors = [t if t is None or t.is_contiguous() else t.contiguous() for t in tensors]
    alive.extend(tensors)
    dummy = state.ws.dummy(float)
    arrays = [dummy if t is None else state.array(t, t.numel(), wp.float32) for t in tensors]  # flat, memoised
    widths = (primitives[2].shape[1], 3 * primitives[4].shape[1], 0 if features is None else features.shape[1])
    return fast.InputCheck(arrays, widths, 0 if background is None else 3, raise_flagged)


class FastRasterizeFunction(torch.autograd.Function):
    """The 3D op through `fast_pipeline` (tests/legacy_raster.py holds a per-call op it must match bit for bit).
    check: None, or the caller's (features, K, background) when the finite-value checks run in the pipeline."""

    @staticmethod
    def forward(ctx, settings, wanted, options, means, quats, scales, opacities, coeffs, features, viewmat,
                intrinsics, means2d_probe, check=None):
        needs = ctx.needs_input_grad[3:11]
        any_grad = any(ctx.needs_input_grad[3:])
        device = means.device
        state = device_state(device)
        ws = state.ws
        nf = wanted.num_features
        layout = fast.feature_layout(state.wdev)
        (means, quats, scales, opacities, coeffs, features), viewmat, intrinsics = detached_inputs(
            ctx, (means, quats, scales, opacities, coeffs, features), viewmat, intrinsics)
        desc = state.desc
        view, intr, check = staged_camera(state, viewmat, intrinsics, check)
        inputs = projection_inputs(state, (means, quats, scales, coeffs, view, intr), wp.vec3)
        w_opac = desc(opacities, wp.float32)
        w_feat = _features_arg(features, nf, layout, state)

        keep = ws.lease_frame() if any_grad else None  # back to the pool with ctx.state
        (color, alpha, depth, inv_depth, feats), zacc, outputs = image_outputs(state, means, settings, wanted,
                                                                               layout, keep)

        alive = []
        checks = None if check is None else input_check(state, (means, quats, scales, opacities, coeffs), view,
                                                        check, alive)
        overflowed, overflow = overflow_flag(state, options, means)
        with state.scope():
            frame = fast.forward(ws, settings, wanted, inputs, w_opac, w_feat, outputs, keep, check=checks,
                                 deterministic=options.deterministic, overflow=overflow)
            visible = state.tensor(frame.counts) > 0
            if means2d_probe is not None:  # gives the probe the projected centres; its grad is dL/dmeans2d
                means2d_probe.data.copy_(state.tensor(frame.means2d).view(-1, 2))
            fast._stage(None, "outputs (torch)")
        count = frame.total  # a plain int (-1: not read, speculative): autograd passes it through
        ctx.mark_non_differentiable(visible)
        if overflowed is not None:
            ctx.mark_non_differentiable(overflowed)
        if any_grad:
            ctx.absgrad = getattr(means2d_probe, "absgrad", None) if wanted.absgrad else None
            ctx.state = (frame, keep, zacc, settings, wanted, options, needs, layout)
            ctx.save_for_backward(means, quats, scales, opacities, coeffs, features, viewmat, intrinsics)
            ctx.forward_state = state
        return color, alpha, depth, inv_depth, feats, visible, count, overflowed

    @staticmethod
    @differentiable_once("the 3D render (rasterize)")
    def backward(ctx, g_color, g_alpha, g_depth, g_inv, g_feat, _g_visible, _g_count, _g_overflowed):
        fast._stage(None, "between (loss, autograd)")
        frame, keep, zacc, settings, wanted, options, needs, layout = take_backward_state(ctx)
        saved = ctx.saved_tensors  # unpacked once: each read of ctx.saved_tensors unpacks them again
        means, quats, scales, opacities, coeffs, features, viewmat, intrinsics = saved
        state = backward_state(ctx.forward_state)
        ws = state.ws
        nf = wanted.num_features

        # the blend adjoint is launched before the gradients' torch views are made: the GPU waits for that launch
        gradients = GradientBlock(saved, ctx.camera_shapes, needs)
        desc = state.desc
        alive = []  # descriptors hold no reference: contiguous copies must outlive the launches

        w_opac = desc(opacities, wp.float32)
        w_feat = _features_arg(features, nf, layout, state)
        adj_opac = state.array_at(gradients.address(OPACITIES), opacities.shape[0], wp.float32)
        adj_feat = feature_gradient_at(gradients.address(FEATURES), features.shape[0], nf, layout, state)
        probe_grad = None
        with state.scope():
            upstream = blend_upstream(state, layout, alive, settings, wanted,
                                      (g_color, g_alpha, g_depth, g_inv, g_feat))
            projected = fast.blend_backward(ws, frame, settings, wanted, w_opac, w_feat, upstream,
                                            adj_opac, adj_feat, features.shape[0], options.backward_kernel, zacc=zacc)
            grads, g_opac, g_features = gradients.views()
            if wanted.absgrad:  # Σ over pixels of |dL/dmeans2d|, into the probe's buffer (rasterize(absgrad=True))
                absgrad = projected.pop()
                if ctx.absgrad is not None:
                    ctx.absgrad.add_(state.tensor(absgrad).view(-1, 2))
            if ctx.needs_input_grad[11]:  # dL/dmeans2d, read before the projection adjoint
                probe_grad = state.tensor(projected[0]).view(-1, 2).clone()
            if any(needs[i] for i in (0, 1, 2, 4, 6, 7)):
                projection_adjoint(state, fast.project_backward, frame, settings,
                                   (means, quats, scales, coeffs, viewmat, intrinsics), grads, needs, projected,
                                   wp.vec3)
        grads[3] = g_opac if needs[3] else None
        grads[5] = g_features if needs[5] else None
        return (None, None, None) + tuple(grads) + (probe_grad, None)
