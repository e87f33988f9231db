"""The two torch ops of the render cut at the projected splats (`render/splats.py`), over the lean pipeline the whole
3D op uses (`fast_pipeline`): the projection kernel and its generated adjoint, and the binning, sort, blend and the
hand-written blend adjoints (per-warp sums on GPUs) with buffers reused across calls. Model-parallel training renders
through these, so a sharded render costs what a whole one does, plus the exchange.

Both ops work on packed splat rows, the layout ranks exchange (`COLUMNS`): the projection writes its outputs into
their columns (Warp arrays over the strided columns) and the blend unpacks them in one launch into the contiguous
arrays its GPU kernels' tile loads need (`kernels/splat_rows.py`), so no torch op packs or unpacks a column and
autograd sees one tensor of rows each way. Lifetimes are those of `gaussians_fast`: the blend's backward reads buffers lent
to the render for as long as its autograd context lives; outputs and gradients handed back are fresh tensors."""
from __future__ import annotations

import torch
import warp as wp

from warpgs.kernels import project, splat_rows
from warpgs.render import fast_pipeline as fast
from warpgs.render.differentiable_once import differentiable_once
from warpgs.render.device_state import device_state
from warpgs.render.gaussians_fast import (_PROJECTION_DTYPES, _features_arg, blend_upstream,
                                          feature_gradient_arg, image_outputs, projection_inputs, take_backward_state)

# A splat row: (first column, width, Warp dtype) of each field; the features follow from column SPLAT_COLUMNS on.
_DTYPES = {"means2d": wp.vec2, "conics": wp.vec3, "cov2d": wp.vec3, "depths": wp.float32, "colors": wp.vec3,
           "opacities": wp.float32}
COLUMNS = {name: (*splat_rows.LAYOUT[name], dtype) for name, dtype in _DTYPES.items()}  # (first, width, dtype)
SPLAT_COLUMNS = splat_rows.SPLAT_COLUMNS
_PROJECTED = ("means2d", "conics", "cov2d", "depths", "colors")  # the projection kernel's outputs, in its order
_PROJECTED_GRADS = ("means2d", "conics", "colors", "depths")  # what its adjoint and the blend adjoint exchange


def column(rows: torch.Tensor, name: str) -> torch.Tensor:
    """The [N] or [N, width] view of one field of packed rows."""
    first, width, _ = COLUMNS[name]
    return rows[:, first] if width == 1 else rows[:, first:first + width]


def _column_array(state, rows: torch.Tensor, name: str):
    return state.desc(column(rows, name), COLUMNS[name][2])


class FastProjectRowsFunction(torch.autograd.Function):
    """apply(settings, means, quats, scales, coeffs, viewmat [4,4], intrinsics [4], opacities, features) -> (rows
    [N, 13 + C], valid [N] bool): every primitive's splat row (opacity and features copied in); the cov2d columns
    carry no gradient."""

    @staticmethod
    def forward(ctx, settings, means, quats, scales, coeffs, viewmat, intrinsics, opacities, features):
        state = device_state(means.device)
        n = means.shape[0]
        tensors = [t.contiguous() for t in (means, quats, scales, coeffs)]
        camera = [viewmat.reshape(1, 4, 4).contiguous(), intrinsics.reshape(1, 4).contiguous()]
        rows = means.new_empty(n, SPLAT_COLUMNS + features.shape[1])
        valid = torch.empty(n, dtype=torch.int32, device=means.device)
        outs = [_column_array(state, rows, name) for name in _PROJECTED] + [state.desc(valid, wp.int32)]
        inputs = projection_inputs(state, tensors + camera, wp.vec3)
        with state.scope():
            state.ws.launches.launch("split_project", project.project_gaussians, n,
                                     fast.projection_args(settings, inputs, outs))
        column(rows, "opacities").copy_(opacities)
        rows[:, SPLAT_COLUMNS:].copy_(features)
        is_valid = valid > 0
        ctx.mark_non_differentiable(is_valid)
        ctx.save_for_backward(*tensors, *camera)
        ctx.settings, ctx.camera_shapes = settings, (viewmat.shape, intrinsics.shape)
        return rows, is_valid

    @staticmethod
    @differentiable_once("the split render's projection (project_rows)")
    def backward(ctx, g_rows, _g_valid):
        saved = ctx.saved_tensors
        needs = ctx.needs_input_grad[1:7]
        n = saved[0].shape[0]
        grads = [torch.zeros_like(t) if need else None for t, need in zip(saved, needs)]
        if g_rows is not None:
            g_rows = g_rows.contiguous()
        if n and any(needs) and g_rows is not None:
            state = device_state(saved[0].device)
            ws = state.ws
            upstream = [_column_array(state, g_rows, name) for name in _PROJECTED_GRADS]
            scratch = [ws.array(f"split_replay_{name}", n, COLUMNS[name][2]) for name in _PROJECTED]
            input_grads = [None if g is None else state.desc(g, wp.vec3 if dt is None else dt)
                           for g, dt in zip(grads, _PROJECTION_DTYPES)]
            with state.scope():
                fast.launch_projection_adjoint(ws, "split_project_adjoint", ctx.settings, n,
                                               projection_inputs(state, list(saved), wp.vec3),
                                               scratch + [ws.array("split_replay_valid", n, wp.int32)],
                                               input_grads, upstream)
        view_shape, intr_shape = ctx.camera_shapes
        if grads[4] is not None:
            grads[4] = grads[4].view(view_shape)
        if grads[5] is not None:
            grads[5] = grads[5].view(intr_shape)
        g_opacities = g_features = None
        if g_rows is not None:
            g_opacities = column(g_rows, "opacities") if ctx.needs_input_grad[7] else None
            g_features = g_rows[:, SPLAT_COLUMNS:] if ctx.needs_input_grad[8] else None
        return (None,) + tuple(grads) + (g_opacities, g_features)


class FastBlendRowsFunction(torch.autograd.Function):
    """apply(settings, wanted, options, rows) -> (color, alpha, depth, inv_depth, features, visible) of n >= 1
    valid splat rows (features: the first wanted.num_features feature columns), as the whole op's blend gives them
    (depth already divided by alpha; empty tensors for outputs not wanted). options: the RasterOptions of the call
    (deterministic binning; the GPU blend adjoint's kernel), as the whole op takes them."""

    @staticmethod
    def forward(ctx, settings, wanted, options, rows):
        state = device_state(rows.device)
        ws = state.ws
        rows = rows.contiguous()
        n, nf = rows.shape[0], wanted.num_features
        layout = fast.feature_layout(state.wdev)
        keep = ws.lease_frame() if ctx.needs_input_grad[3] else None
        per_call = keep if keep is not None else ws
        fields = [per_call(f"split_{name}", n, COLUMNS[name][2]) for name in _PROJECTED + ("opacities",)]
        valid = ws.array("split_valid", n, wp.int32)
        (color, alpha, depth, inv_depth, feats), zacc, outputs = image_outputs(state, rows, settings, wanted, layout,
                                                                               keep)
        with state.scope():
            ws.launches.launch("unpack_splat_rows", splat_rows.unpack_splat_rows, n,
                               [state.desc(rows, wp.float32)] + fields)
            valid.fill_(1)  # every row handed in is valid (render/splats.py drops the others first)
            frame = fast.bin_and_blend(ws, settings, wanted, tuple(fields[:5]) + (valid,), fields[5],
                                       _features_arg(rows[:, SPLAT_COLUMNS:SPLAT_COLUMNS + nf], nf, layout, state),
                                       outputs, keep, deterministic=options.deterministic)
            visible = state.tensor(frame.counts) > 0
        ctx.mark_non_differentiable(visible)
        if keep is not None:
            ctx.state = (frame, keep, zacc, settings, wanted, options, layout, fields[5])
            ctx.save_for_backward(rows)  # its features columns are read in place
        return color, alpha, depth, inv_depth, feats, visible

    @staticmethod
    @differentiable_once("the split render's blend (blend_rows)")
    def backward(ctx, g_color, g_alpha, g_depth, g_inv, g_feat, _g_visible):
        frame, keep, zacc, settings, wanted, options, layout, opacities = take_backward_state(ctx)
        (rows,) = ctx.saved_tensors
        state = device_state(rows.device)
        ws, n, nf = state.ws, frame.n, wanted.num_features
        g_opacities = rows.new_zeros(n)  # contiguous: the CPU threads' private sums are merged into it flat
        g_features = rows.new_zeros(n, nf)
        alive = []  # descriptors hold no reference: contiguous copies must outlive the launches
        g_rows = torch.zeros_like(rows)
        with state.scope():
            upstream = blend_upstream(state, layout, alive, settings, wanted,
                                      (g_color, g_alpha, g_depth, g_inv, g_feat))
            projected = fast.blend_backward(
                ws, frame, settings, wanted, opacities,
                _features_arg(rows[:, SPLAT_COLUMNS:SPLAT_COLUMNS + nf], nf, layout, state), upstream,
                state.array(g_opacities, n, wp.float32), feature_gradient_arg(g_features, nf, layout, state), n,
                options.backward_kernel, zacc=zacc)
            for name, a in zip(_PROJECTED_GRADS, projected):  # workspace memory: copied out before the next call
                target = column(g_rows, name)
                target.copy_(state.tensor(a).view(target.shape))
        column(g_rows, "opacities").copy_(g_opacities)
        g_rows[:, SPLAT_COLUMNS:SPLAT_COLUMNS + nf].copy_(g_features)
        return None, None, None, g_rows
