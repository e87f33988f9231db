"""The 3D Gaussian pipeline of `pipeline_gaussians`, driven with as little host work per call as possible.

Same kernels, same maths, same results (the tests compare it bit for bit with a per-call op over
`pipeline_gaussians`, tests/legacy_raster.py); what differs is the host side:
- scratch memory comes from a `Workspace` reused across calls, and nothing is zero-filled that a kernel overwrites
  (tile ranges are written for every tile, projected outputs for every Gaussian);
- what a backward pass reads comes from `keep`: the torch op passes a buffer set lent from the workspace's pool
  until its autograd context lets go of it (`FrameLease`), so a later call never overwrites a buffer that a
  pending backward needs, and steady training reuses one set;
- every launch is a recorded `wp.Launch` replayed with only its changed parameters (`LaunchCache`);
- one host synchronisation per call (the number of tile pairs sizes the sort), through a pinned buffer; the
  input checks' flags (`InputCheck`) are read at that same sync, so checking costs no sync of its own; a
  speculative call (`overflow` given: the trainer's) has none: it sorts into a room sized from earlier counts
  (tile_binning.py, pair_room.py);
- on GPUs, the launches up to that sync (projection, checks, footprints, depth sort, prefix sum, the reads) are
  one CUDA graph, replayed while the arrays and sizes stay the same (workspace.LaunchSequence); a speculative
  call's graph also holds the pair emission, sort and tile ranges;
- no wp.Tape: the backward launches the blend adjoint and then the projection's generated adjoint itself.

Torch-free: arrays come in as Warp arrays or array descriptors (`wp.from_torch(..., return_ctype=True)`). The
binning and the pair sort, which the surfels' pipeline shares, are tile_binning.py's.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import warp as wp

from warpgs.kernels import binning, blend, blend_gpu, input_checks, project, project_adjoint
from warpgs.render.cpu_threads import run_threads
from warpgs.render.defaults import DEPTH_EPS, PER_WARP_ADJOINTS, current_raster_options
from warpgs.render.pair_adjoint import PairOrder, choose_kernel, run_pair_adjoint
from warpgs.render.pipeline_gaussians import (Settings, Wanted, _block_dims, _block_reduce, _cooperative,
                                              _tile_launches, blend_params, projection_color_mode)
from warpgs.render.sort_ahead import settle_ahead, sort_ahead_for
from warpgs.render.tile_binning import Keep, _stage, bin_into_tiles, launch_sequence, pair_order
from warpgs.render.workspace import LaunchSequence, Workspace



@dataclass
class TileFrame:
    """What any primitive kind's forward pass leaves for its backward (in the `keep` buffers when given) and for
    the op's outputs; each kind's frame adds its own projected quantities."""
    n: int
    total: int  # primitive-tile pairs
    means2d: wp.array
    depths: wp.array
    colors: wp.array
    q_cut: wp.array
    tile_start: wp.array
    sorted_ids: wp.array
    transmittance: wp.array
    last: wp.array
    counts: wp.array  # workspace: valid until the next call on this workspace
    pairs: Optional[PairOrder] = field(default=None, kw_only=True)  # set for a deterministic backward (pair_order)


@dataclass
class Frame(TileFrame):
    """The 3D Gaussians' frame."""
    conics: wp.array


@dataclass
class InputCheck:
    """A render's finite-value checks (kernels/input_checks.flag_bad_inputs), read with the tile-pair count.
    arrays: the kernel's nine flat float arrays (1-element dummies for absent ones, with width 0); report(flags)
    raises the error for the FLAG_SLOTS flags when any is set."""
    arrays: list
    widths: tuple  # floats per primitive of (scales, colours, features)
    background_width: int
    report: Callable[[list], None]


def add_input_check(ws: Workspace, seq: LaunchSequence, n: int, check: InputCheck) -> None:
    flags = ws.array("input_flags", input_checks.FLAG_SLOTS, wp.int32)
    seq.zero(flags)
    seq.launch("input_checks", input_checks.flag_bad_inputs, n,
               list(check.arrays) + list(check.widths) + [check.background_width, flags])
    first = seq.read_ints(flags, 0, input_checks.FLAG_SLOTS)
    seq.on_values(lambda values: check.report(values[first: first + input_checks.FLAG_SLOTS]))


def forward(ws: Workspace, s: Settings, want: Wanted, inputs, opacities, features, outputs, keep: Optional[Keep],
            on_stage: Optional[Callable[[str], None]] = None, check: Optional[InputCheck] = None,
            deterministic: bool = False, overflow=None) -> Frame:
    """Projects, bins, sorts and blends. inputs: (means, quats, scales, coeffs, viewmat, intrinsics) as the
    projection kernel takes them; outputs: (color, alpha, depth accumulation, inv_depth, features, expected depth)
    arrays the blend writes (1-element dummies for outputs not asked for; features zeroed beforehand for the
    per-thread CPU kernel; the expected depth, the accumulation over alpha, is written with the rest of the pixel);
    features in the layout of `feature_layout`. keep=None: everything in the workspace (no backward follows).
    on_stage(name), if given, is called after each stage (benchmarks/profile_stages.py times them).
    check: the input checks to run, whose error is raised at the tile-pair count's sync (before anything is sized
    from the count). deterministic: keep what a fixed-order (run-to-run identical) GPU backward needs (pair_order).
    overflow: a 1-element int32 array to bin speculatively into (see sort_into_tiles), else None."""
    _stage(on_stage, "op prologue")  # the render call's host work up to here (checks, wrapping, allocation)
    n = int(inputs[0].shape[0])
    per_call = keep if keep is not None else ws  # both take (name, length, dtype)

    means2d = per_call("means2d", n, wp.vec2)
    conics = per_call("conics", n, wp.vec3)
    depths = per_call("depths", n, float)
    colors = per_call("colors", n, wp.vec3)
    cov2d = ws.array("cov2d", n, wp.vec3)
    valid = ws.array("valid", n, wp.int32)
    seq = launch_sequence(ws, on_stage)
    seq.launch("project", project.project_gaussians, n,
               projection_args(s, inputs, (means2d, conics, cov2d, depths, colors, valid)))
    if check is not None:
        add_input_check(ws, seq, n, check)
    _stage(on_stage, "project")
    return bin_and_blend(ws, s, want, (means2d, conics, cov2d, depths, colors, valid), opacities, features, outputs,
                         keep, on_stage, seq, deterministic, overflow)


def bin_and_blend(ws: Workspace, s: Settings, want: Wanted, projected, opacities, features, outputs,
                  keep: Optional[Keep], on_stage: Optional[Callable[[str], None]] = None,
                  sequence: Optional[LaunchSequence] = None, deterministic: bool = False, overflow=None) -> Frame:
    """The forward after the projection: bins, sorts and blends projected Gaussians. projected: (means2d, conics,
    cov2d, depths, colors, valid) arrays of n rows, from the projection kernel or from anywhere (render/splats.py);
    the rest as `forward` takes it. sequence: launches already queued (run with the binning, up to the sync)."""
    means2d, conics, cov2d, depths, colors, valid = projected
    dev = ws.device
    n = int(depths.shape[0])
    L = ws.launches
    per_call = keep if keep is not None else ws
    ahead = sort_ahead_for(overflow, deterministic)
    counts, q_cut, total, tile_start, tile_end, sorted_ids = bin_into_tiles(
        ws, "footprints", binning.tile_footprints, [means2d, cov2d, opacities, valid], depths, s, per_call,
        on_stage, sequence=sequence, overflow=None if deterministic else overflow, ahead=ahead)
    pairs = pair_order(ws, s, keep, n, total, sorted_ids) if deterministic else None

    npix = s.width * s.height
    transmittance = per_call("transmittance", npix, float)
    last = per_call("last", npix, wp.int32)
    color, alpha, depth, inv_depth, out_features, expected_depth = outputs
    kernel, block_dim = _blend_kernel(dev, s, want, backward=False)
    tail = [color, transmittance, alpha, depth, expected_depth, inv_depth, out_features, last]

    def blend(tile_start, tile_end, sorted_ids):
        head = [tile_start, tile_end, sorted_ids, means2d, conics, opacities, colors, depths, features, q_cut]

        def work(thread, chunks):  # each chunk writes only its own pixels
            for c, (first, count) in enumerate(chunks):
                L.launch(("blend_fwd", thread, c), kernel, count * s.tile_size**2,
                         head + [_params(ws, s, want, first, DEPTH_EPS)] + tail, block_dim)

        run_threads(work, _tile_launches(s, dev))

    blend(tile_start, tile_end, sorted_ids)
    total, tile_start, sorted_ids = settle_ahead(ahead, total, tile_start, sorted_ids, blend)
    _stage(on_stage, "blend forward")
    return Frame(n=n, total=total, means2d=means2d, conics=conics, depths=depths, colors=colors, q_cut=q_cut,
                 tile_start=tile_start, sorted_ids=sorted_ids, transmittance=transmittance, last=last,
                 counts=counts, pairs=pairs)


def blend_backward(ws: Workspace, frame: Frame, s: Settings, want: Wanted, opacities, features, upstream,
                   adj_opacities, adj_features, num_features_rows: int, backward_kernel: str = "warp_sums", *,
                   zacc=None):
    """The blending adjoint. upstream: (grad color, alpha, depth, inv_depth, features) in the kernels' layouts
    (dummies for outputs not rendered); zacc: the forward's depth accumulation, given when the depth upstream is the
    expected depth's (the blend wrote the division, whose adjoint the kernels then run per pixel). adj_opacities /
    adj_features: where the opacity and feature gradients accumulate (zeroed by the caller). Returns the projected
    gradients (means2d, conics, colors, depths, and with want.absgrad each Gaussian's Σ over pixels of |d means2d|),
    in the workspace: valid until the next backward on it. A frame
    with `pairs` (forward(deterministic=True)) gets the fixed-order adjoint of pair_adjoint.py."""
    L = ws.launches
    kernel, block_dim = _blend_kernel(ws.device, s, want, backward=True, variant=backward_kernel)
    parts = 1
    if frame.pairs is not None:
        kernel, block_dim, parts = choose_kernel(blend_gpu, s.tile_size, backward_kernel, _block_dims(s)[1],
                                                 want.num_features, absgrad=want.absgrad)
    head = [frame.tile_start, frame.sorted_ids, frame.means2d, frame.conics, opacities, frame.colors, frame.depths,
            features, frame.q_cut]
    tail = [frame.transmittance, frame.last, ws.dummy(float) if zacc is None else zacc] + list(upstream)
    depth_eps = 0.0 if zacc is None else DEPTH_EPS
    # |d means2d| summed per Gaussian (want.absgrad): a field of its own, else a placeholder the kernel never writes
    no_absgrad = [] if want.absgrad else [ws.dummy(wp.vec2)]

    # the per-warp kernels' last argument: for the scatter sums the fields' block as one flat array (the fields
    # below, in blend_gpu.SCATTER_LAYOUT's order), else a placeholder; the other kernels have no such argument
    takes_block = warp_sums_kernel(ws.device, s, backward_kernel)
    scatter = takes_block and frame.pairs is None and scatter_sums(backward_kernel, want)

    def launch(key, first, count, targets):
        block = [scatter_block_arg(ws, key, targets, OWN_FLOATS * frame.n, scatter)] if takes_block else []
        L.launch(key, kernel, count * s.tile_size**2,
                 head + [_params(ws, s, want, first, depth_eps)] + tail + targets + no_absgrad + block, block_dim)

    fields = ADJOINT_FIELDS + ([("means2d_abs", 2, wp.vec2)] if want.absgrad else [])
    projected = run_blend_adjoint(ws, s, "blend_bwd", fields, frame.n, adj_opacities, adj_features,
                                  num_features_rows, want.num_features, launch, frame.pairs, parts)
    _stage(None, "blend backward")
    return projected


OPACITIES, FEATURES = "opacities", "features"  # where a blend adjoint takes the caller's gradient arrays
# The 3D blend adjoint's gradient targets in its kernels' argument order (run_blend_adjoint's `fields`); the scatter
# kernel's SCATTER_LAYOUT follows this order (tests/test_warp_ops.py checks it).
ADJOINT_FIELDS = [("means2d", 2, wp.vec2), ("conics", 3, wp.vec3), OPACITIES, ("colors", 3, wp.vec3),
                  ("depths", 1, float), FEATURES]
OWN_FLOATS = sum(f[1] for f in ADJOINT_FIELDS if isinstance(f, tuple))  # floats per primitive in the block


def run_blend_adjoint(ws: Workspace, s: Settings, key: str, fields, n: int, adj_opacities, adj_features,
                      num_features_rows: int, num_features: int, launch, pairs: Optional[PairOrder] = None,
                      parts: int = 1) -> list:
    """Runs a blend adjoint over the tiles (one launch on GPUs, a few threads on the CPU) and returns its sums per
    primitive. fields: the kernel's gradient targets in its argument order, each (name, floats per primitive,
    dtype) summed in one zeroed workspace block, or OPACITIES / FEATURES for the caller's arrays.
    launch(key, first_tile, tile_count, targets) makes one launch.

    CPU threads would race on the sums (Warp's CPU atomics are plain adds), so threads other than the first
    accumulate into private workspace buffers (the fields, then opacities, then features) added in afterwards.
    The returned views are workspace memory: valid until the next backward on it.
    pairs: the deterministic adjoint instead (one launch; `parts` summing groups per tile; pair_adjoint.py)."""
    if pairs is not None:
        caller = {OPACITIES: (adj_opacities, True), FEATURES: (adj_features, num_features > 0)}
        return run_pair_adjoint(ws, key, fields, n, pairs, parts, caller, s.num_tiles, launch)
    width = sum(f[1] for f in fields if f not in (OPACITIES, FEATURES))
    block = ws.array("grad_projected", width * n, float)
    block.zero_()

    def targets(prefix, base, opacities, features):
        out, offset = [], 0
        for f in fields:
            if f in (OPACITIES, FEATURES):
                out.append(opacities if f == OPACITIES else features)
                continue
            name, floats, dtype = f
            out.append(ws.view(f"{key}_{prefix}_{name}", base, offset * n, n, dtype))
            offset += floats
        return out

    per_thread = _tile_launches(s, ws.device)
    per_target = [targets("sum", block, adj_opacities, adj_features)]
    private_size = (width + 1) * n + num_features_rows * max(num_features, 1)
    for t in range(1, len(per_thread)):
        private = ws.array(f"grad_private{t}", private_size, float)
        private.zero_()
        feats = (ws.view(f"{key}_p{t}_features", private, (width + 1) * n, (num_features_rows, num_features), float)
                 if num_features else ws.dummy(float, 2))
        per_target.append(targets(f"p{t}", private, ws.view(f"{key}_p{t}_opacities", private, width * n, n, float),
                                  feats))

    def work(thread, chunks):
        for c, (first, count) in enumerate(chunks):
            launch((key, thread, c), first, count, per_target[thread])

    run_threads(work, per_thread)
    L = ws.launches
    for t in range(1, len(per_thread)):
        private = ws.array(f"grad_private{t}", private_size, float)
        L.launch(("merge_projected", t), blend.accumulate, width * n, [private, block])
        L.launch(("merge_opacities", t), blend.accumulate, n,
                 [ws.view(f"{key}_p{t}_opacities", private, width * n, n, float),
                  _flat(ws, "adj_opacities_flat", adj_opacities)])
        if num_features:
            L.launch(("merge_features", t), blend.accumulate, num_features_rows * num_features,
                     [ws.view(f"{key}_p{t}_features_flat", private, (width + 1) * n,
                              num_features_rows * num_features, float),
                      _flat(ws, "adj_features_flat", adj_features)])
    return [v for v, f in zip(per_target[0], fields) if f not in (OPACITIES, FEATURES)]


def project_backward(ws: Workspace, frame: Frame, s: Settings, inputs, input_grads, projected_grads) -> None:
    """The projection's generated adjoint (what wp.Tape.backward would run). input_grads: the gradient arrays of
    `inputs` (None where not wanted); projected_grads: (means2d, conics, colors, depths) from `blend_backward`."""
    n = frame.n
    outs = (frame.means2d, frame.conics, ws.array("cov2d", n, wp.vec3), frame.depths, frame.colors,
            ws.array("valid", n, wp.int32))
    launch_projection_adjoint(ws, "project_adjoint", s, n, inputs, outs, input_grads, projected_grads)
    _stage(None, "project adjoint")


def projection_args(s: Settings, inputs, outs) -> list:
    """The projection kernel's arguments: inputs (means, quats, scales, coeffs, viewmat, intrinsics), the settings,
    outs (means2d, conics, cov2d, depths, colors, valid)."""
    color_mode = projection_color_mode(s)
    return list(inputs) + [s.width, s.height, s.near, s.far, color_mode, max(s.sh_degree, 0), s.low_pass] + list(outs)


def launch_projection_adjoint(ws: Workspace, key: str, s: Settings, n: int, inputs, outs, input_grads,
                              projected_grads) -> None:
    """The projection kernel's generated adjoint, run only for the Gaussians with an upstream gradient
    (`project_gaussians_reached`). outs: arrays its forward replay may write (the forward's own or scratch);
    input_grads: the gradient arrays of `inputs` (None where not wanted), zero-filled by the caller; projected_grads:
    upstream (means2d, conics, colors, depths), also read to pick the Gaussians."""
    g_means2d, g_conics, g_colors, g_depths = projected_grads
    if (current_raster_options().project_adjoint == "written" and input_grads[4] is None and input_grads[5] is None
            and inputs[4].shape[0] == 1):  # one camera, not differentiated: the written-out adjoint covers it
        launch_written_projection_adjoint(ws, key, s, n, inputs, input_grads, projected_grads)
        return
    adj = list(input_grads) + [0, 0, 0.0, 0.0, 0, 0, 0.0, g_means2d, g_conics, None, g_depths, g_colors, None]
    args = projection_args(s, inputs, outs) + [g_means2d, g_conics, g_colors, g_depths]
    ws.launches.launch_adjoint(key, project.project_gaussians_reached, n, args, adj + [None] * 4)


def launch_written_projection_adjoint(ws: Workspace, key: str, s: Settings, n: int, inputs, input_grads,
                                      projected_grads) -> None:
    """kernels/project_adjoint.py's adjoint (one camera, no camera gradient): input_grads (means, quats, scales,
    coeffs; None where not wanted), zero-filled by the caller, get the Gaussians' gradients written (the generated
    adjoint adds into them: the same result from zeros)."""
    want = 0
    grads = []
    for bit, g, dtype, ndim in zip((project_adjoint.WANT_MEANS, project_adjoint.WANT_QUATS,
                                     project_adjoint.WANT_SCALES, project_adjoint.WANT_COEFFS), input_grads[:4],
                                   (wp.vec3, wp.vec4, wp.vec3, wp.vec3), (1, 1, 1, 2)):
        if g is None:  # a placeholder the kernel never writes
            g = ws.dummy(dtype, ndim)
        else:
            want |= bit
        grads.append(g)
    color_mode = projection_color_mode(s)
    ws.launches.launch(key + "_written", project_adjoint.project_gaussians_adjoint, n,
                       list(inputs) + [s.width, s.height, s.near, color_mode, max(s.sh_degree, 0), s.low_pass]
                       + list(projected_grads) + [want] + grads)


def _flat(ws: Workspace, name: str, a):
    """A float32 array `a` (Warp array) seen as one flat run of floats."""
    if isinstance(a, wp.array):
        return ws.view(name, a, 0, a.size * (wp.types.type_size_in_bytes(a.dtype) // 4), float)
    raise TypeError("expected a Warp array")


def blend_settings_key(s: Settings) -> tuple:
    """The Settings fields every kind's BlendParams is made from (memo keys of the memoised params)."""
    return (s.width, s.height, s.tile_size, s.alpha_min, s.transmittance_min, s.alpha_max)


def _params(ws: Workspace, s: Settings, want: Wanted, first: int, depth_eps: float = 0.0):
    key = ("blend_params", *blend_settings_key(s), want.color, want.depth, want.inv_depth, want.num_features,
           want.absgrad, first, depth_eps)
    return ws.memo(key, lambda: blend_params(s, want, first, depth_eps))


def _blend_kernel(dev, s: Settings, want: Wanted, backward: bool, variant: str = "warp_sums"):
    """(kernel, block_dim): the per-thread CPU kernels, or the cooperative GPU ones (blend_gpu.py). variant: the GPU
    adjoint, "warp_sums" or "scatter" (backward_kernel_warp_sums, tiles of 8x8 and up) or "block" (backward_kernel)."""
    if not _cooperative(dev):
        return (blend.blend_backward if backward else blend.blend_forward), 0
    fwd_block, bwd_block = _block_dims(s)
    if not backward:
        return blend_gpu.forward_kernel(fwd_block, want.num_features), fwd_block
    if warp_sums_kernel(dev, s, variant):
        block = min(s.tile_size**2, 256)
        return blend_gpu.backward_kernel_warp_sums(block, want.num_features, absgrad=want.absgrad,
                                                   scatter=scatter_sums(variant, want)), block
    return blend_gpu.backward_kernel(bwd_block, _block_reduce(), want.num_features), bwd_block


def warp_sums_kernel(dev, s: Settings, variant: str) -> bool:
    """Whether the adjoint `variant` (3D or surfels) runs a backward_kernel_warp_sums here (or its deterministic
    twin): a cooperative device and tiles of whole warps."""
    return _cooperative(dev) and variant in PER_WARP_ADJOINTS and blend_gpu.warp_sums_supported(s.tile_size)


def scatter_block_arg(ws: Workspace, key, targets, floats: int, scatter: bool) -> wp.array:
    """A per-warp adjoint's last argument: with the scatter sums, the launch's gradient block (its first field,
    targets[0], starts it) as `floats` flat floats, else a placeholder the kernel never writes."""
    return ws.view(f"{key}_flat", targets[0], 0, floats, float) if scatter else ws.dummy(float)


def scatter_sums(variant: str, want: Wanted) -> bool:
    """Whether the GPU adjoint `variant` sums by reduce-scatter: "scatter", unless |d means2d| is summed too (AbsGS),
    which the per-lane sums carry."""
    return variant == "scatter" and not want.absgrad


def feature_layout(dev) -> str:
    """How the blend kernels take features: 'vectors' (length-C vectors, cooperative GPU kernels) or 'rows'
    ([rows, C] floats, per-thread CPU kernels)."""
    return "vectors" if _cooperative(dev) else "rows"
