"""The surfel (2DGS) pipeline on Warp arrays: project -> footprint -> the shared tile sort -> blend, and the blend
adjoint, driven the way `fast_pipeline` drives the 3D one: scratch memory from a `Workspace`, what the backward
reads in the buffers `keep` lends, recorded launches replayed, one host synchronisation per call (the sort), and no
wp.Tape (the backward launches the blend adjoint, then the projection's generated adjoint). The tests compare it bit
for bit with a per-call driver of the same kernels (tests/legacy_raster_surfels.py).

Torch-free: arrays come in as Warp arrays or array descriptors."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import warp as wp

from warpgs.kernels import surfel_blend, surfel_blend_gpu, surfel_project, surfel_steps
from warpgs.render.cpu_threads import run_threads
from warpgs.render.defaults import DEPTH_EPS
from warpgs.render.fast_pipeline import (FEATURES, OPACITIES, InputCheck, TileFrame, add_input_check,
                                         blend_settings_key, run_blend_adjoint, scatter_block_arg,
                                         warp_sums_kernel)
from warpgs.render.pair_adjoint import choose_kernel
from warpgs.render.pipeline_gaussians import (Settings, Wanted, _block_dims, _block_reduce, _cooperative,
                                              _tile_launches, blend_params)
from warpgs.render.sort_ahead import settle_ahead, sort_ahead_for
from warpgs.render.tile_binning import Keep, _stage, bin_into_tiles, launch_sequence, pair_order
from warpgs.render.workspace import Workspace

# Blended images in the order the torch ops return them (and take their gradients): (name, channels, Warp dtype).
IMAGES = (("color", 3, wp.vec3), ("alpha", 1, wp.float32), ("depth", 1, wp.float32), ("inv_depth", 1, wp.float32),
          ("normal", 3, wp.vec3), ("median", 1, wp.float32), ("distortion", 1, wp.float32))


@dataclass
class SurfelWanted:
    color: bool
    depth: bool
    inv_depth: bool
    normal: bool
    median: bool
    distortion: bool
    num_features: int
    distortion_scale: float  # m = -distortion_scale / z in the distortion term


def image_wanted(wanted: SurfelWanted, name: str) -> bool:
    """Whether image `name` of IMAGES is rendered (alpha always is)."""
    return name == "alpha" or bool(getattr(wanted, name))


def surfel_blend_params(s: Settings, want: SurfelWanted, first_tile: int,
                        depth_eps: float = 0.0) -> surfel_steps.SurfelBlendParams:
    """The per-launch settings of the surfel blend kernels (CPU and GPU, forward and backward). depth_eps > 0: the
    forward also writes the expected depth (accumulation / max(alpha, depth_eps))."""
    sp = surfel_steps.SurfelBlendParams()
    sp.base = blend_params(s, Wanted(color=want.color, depth=want.depth, inv_depth=want.inv_depth,
                                     num_features=want.num_features), first_tile, depth_eps)
    sp.near, sp.dist_scale, sp.filter_inv = s.near, want.distortion_scale, 1.0 / (s.screen_sigma * s.screen_sigma)
    sp.want_normal, sp.want_median, sp.want_distortion = int(want.normal), int(want.median), int(want.distortion)
    return sp

# The blend adjoint's gradient targets, in its argument order (see run_blend_adjoint).
ADJOINT_FIELDS = [("transforms", 9, wp.mat33), ("means2d", 2, wp.vec2), ("depths", 1, float), OPACITIES,
                  ("colors", 3, wp.vec3), ("normals", 3, wp.vec3), FEATURES]
OWN_FLOATS = sum(f[1] for f in ADJOINT_FIELDS if isinstance(f, tuple))  # floats per surfel in the block


@dataclass
class SurfelFrame(TileFrame):
    """The surfels' frame."""
    transforms: wp.array
    normals: wp.array
    median_index: wp.array  # a dummy unless the median depth was rendered
    dist_stats: wp.array  # a dummy unless the distortion was rendered


def forward(ws: Workspace, s: Settings, want: SurfelWanted, inputs, opacities, features, outputs,
            keep: Optional[Keep], check: Optional[InputCheck] = None, deterministic: bool = False,
            overflow=None) -> SurfelFrame:
    """Projects, bins, sorts and blends. inputs: (means, quats, scales, coeffs, viewmat, intrinsics) as the
    projection kernel takes them; outputs: (color, alpha, depth accumulation, inv_depth, normal, median, distortion,
    features, expected depth) arrays the blend writes (1-element dummies for outputs not asked for; features zeroed
    beforehand for the per-thread CPU kernel; the expected depth is the accumulation over alpha). keep=None:
    everything in the workspace (no backward follows). check: the input checks, raised at the tile-pair count's sync
    (fast_pipeline.InputCheck). deterministic: keep what a fixed-order GPU
    backward needs (tile_binning.pair_order). overflow: a 1-element int32 array to bin speculatively into
    (tile_binning.sort_into_tiles), else None."""
    L = ws.launches
    n = int(inputs[0].shape[0])

    per_call = keep if keep is not None else ws  # both take (name, length, dtype)

    transforms = per_call("transforms", n, wp.mat33)
    means2d = per_call("means2d", n, wp.vec2)
    depths = per_call("depths", n, float)
    normals = per_call("normals", n, wp.vec3)
    colors = per_call("colors", n, wp.vec3)
    valid = ws.array("surfel_valid", n, wp.int32)
    seq = launch_sequence(ws)  # up to the sync: one graph on GPUs
    seq.launch("surfel_project", surfel_project.project_surfels, n,
               list(inputs) + _projection_settings(s) + [transforms, means2d, depths, normals, colors, valid])
    if check is not None:
        add_input_check(ws, seq, n, check)
    _stage(None, "surfel project")
    ahead = sort_ahead_for(overflow, deterministic)
    counts, q_cut, total, tile_start, tile_end, sorted_ids = bin_into_tiles(
        ws, "surfel_footprints", surfel_project.surfel_footprints,
        [transforms, means2d, opacities, valid, 1.0 / (s.screen_sigma * s.screen_sigma), s.near], depths,
        s, per_call, sequence=seq, overflow=None if deterministic else overflow, ahead=ahead)
    pairs = pair_order(ws, s, keep, n, total, sorted_ids) if deterministic else None

    npix = s.width * s.height
    transmittance = per_call("transmittance", npix, float)
    last = per_call("last", npix, wp.int32)
    median_index = per_call("median_index", npix, wp.int32) if want.median else ws.dummy(wp.int32)
    dist_stats = per_call("dist_stats", npix, wp.vec3) if want.distortion else ws.dummy(wp.vec3)
    color, alpha, depth, inv_depth, normal, median, distortion, out_features, expected_depth = outputs
    kernel, block_dim = _blend_kernel(ws.device, s, want, backward=False)
    tail = [color, transmittance, alpha, depth, expected_depth, inv_depth, normal, median, median_index, distortion,
            dist_stats, out_features, last]

    def blend(tile_start, tile_end, sorted_ids):
        head = [tile_start, tile_end, sorted_ids, transforms, means2d, depths, opacities, colors, normals, features,
                q_cut]

        def work(thread, chunks):  # each chunk writes only its own pixels
            for c, (first, count) in enumerate(chunks):
                L.launch(("surfel_blend_fwd", thread, c), kernel, count * s.tile_size**2,
                         head + [_params(ws, s, want, first, DEPTH_EPS)] + tail, block_dim)

        run_threads(work, _tile_launches(s, ws.device))

    blend(tile_start, tile_end, sorted_ids)
    total, tile_start, sorted_ids = settle_ahead(ahead, total, tile_start, sorted_ids, blend)
    _stage(None, "surfel blend forward")
    return SurfelFrame(n=n, total=total, transforms=transforms, means2d=means2d, depths=depths, normals=normals,
                       colors=colors, q_cut=q_cut, tile_start=tile_start, sorted_ids=sorted_ids,
                       transmittance=transmittance, last=last, median_index=median_index, dist_stats=dist_stats,
                       counts=counts, pairs=pairs)


def blend_backward(ws: Workspace, frame: SurfelFrame, s: Settings, want: SurfelWanted, opacities, features,
                   upstream, adj_opacities, adj_features, num_features_rows: int, backward_kernel: str = "warp_sums",
                   *, zacc=None):
    """The blending adjoint. upstream: (grad color, alpha, depth, inv_depth, normal, median, distortion, features)
    in the kernels' layouts (dummies for outputs not rendered); zacc: the forward's depth accumulation, given when
    the depth upstream is the expected depth's (fast_pipeline.blend_backward). adj_opacities / adj_features: where
    the opacity and feature gradients accumulate (zeroed by the caller). backward_kernel: the GPU adjoint, "block",
    "warp_sums" or "scatter" (tiles of 8x8 and up). Returns the projected gradients (transforms, means2d, depths, colors,
    normals), in the workspace: valid until the next backward on it. A frame with `pairs` gets the fixed-order
    adjoint (pair_adjoint.py)."""
    L = ws.launches
    kernel, block_dim = _blend_kernel(ws.device, s, want, backward=True, variant=backward_kernel)
    parts = 1
    if frame.pairs is not None:
        kernel, block_dim, parts = choose_kernel(surfel_blend_gpu, s.tile_size, backward_kernel, _block_dims(s)[1],
                                                 want.num_features)
    head = [frame.tile_start, frame.sorted_ids, frame.transforms, frame.means2d, frame.depths, opacities,
            frame.colors, frame.normals, features, frame.q_cut]
    tail = ([frame.transmittance, frame.last, frame.median_index, frame.dist_stats,
             ws.dummy(float) if zacc is None else zacc] + list(upstream))
    depth_eps = 0.0 if zacc is None else DEPTH_EPS

    # the per-warp kernels' last argument: for the scatter sums the fields' block as one flat array (ADJOINT_FIELDS'
    # own fields, in surfel_blend_gpu.SCATTER_LAYOUT's order), else a placeholder; the block kernels have none
    takes_block = warp_sums_kernel(ws.device, s, backward_kernel)
    scatter = takes_block and frame.pairs is None and backward_kernel == "scatter"

    def launch(key, first, count, targets):
        block = [scatter_block_arg(ws, key, targets, OWN_FLOATS * frame.n, scatter)] if takes_block else []
        L.launch(key, kernel, count * s.tile_size**2,
                 head + [_params(ws, s, want, first, depth_eps)] + tail + targets + block, block_dim)

    projected = run_blend_adjoint(ws, s, "surfel_blend_bwd", ADJOINT_FIELDS, frame.n, adj_opacities, adj_features,
                                  num_features_rows, want.num_features, launch, frame.pairs, parts)
    _stage(None, "surfel blend backward")
    return projected


def project_backward(ws: Workspace, frame: SurfelFrame, s: Settings, inputs, input_grads, projected_grads) -> None:
    """The projection's generated adjoint (what wp.Tape.backward would run), for the surfels with an upstream
    gradient only (`project_surfels_reached`). input_grads: the gradient arrays of `inputs` (None where not wanted);
    projected_grads: what `blend_backward` returned."""
    g_transforms, g_means2d, g_depths, g_colors, g_normals = projected_grads
    valid = ws.array("surfel_valid", frame.n, wp.int32)
    args = list(inputs) + _projection_settings(s) + [frame.transforms, frame.means2d, frame.depths, frame.normals,
                                                     frame.colors, valid]
    adj = list(input_grads) + [0.0, 0.0, 0, 0, g_transforms, g_means2d, g_depths, g_normals, g_colors, None]
    args += [g_transforms, g_means2d, g_depths, g_normals, g_colors]
    ws.launches.launch_adjoint("surfel_project_adjoint", surfel_project.project_surfels_reached, frame.n, args,
                               adj + [None] * 5)
    _stage(None, "surfel project adjoint")


def _projection_settings(s: Settings) -> list:
    color_mode = surfel_project.COLOR_SH if s.sh_degree >= 0 else surfel_project.COLOR_DIRECT
    return [s.near, s.far, color_mode, max(s.sh_degree, 0)]


def _params(ws: Workspace, s: Settings, want: SurfelWanted, first: int, depth_eps: float = 0.0):
    key = ("surfel_blend_params", *blend_settings_key(s), s.near, s.screen_sigma, want.color, want.depth,
           want.inv_depth, want.normal, want.median, want.distortion, want.num_features, want.distortion_scale, first,
           depth_eps)
    return ws.memo(key, lambda: surfel_blend_params(s, want, first, depth_eps))


def _blend_kernel(dev, s: Settings, want: SurfelWanted, backward: bool, variant: str = "warp_sums"):
    """(kernel, block_dim): the per-thread CPU kernels (block_dim 1, as the tests' per-call driver launches them, so
    both share one compiled module), or the cooperative GPU ones of surfel_blend_gpu.py (variant: the adjoint)."""
    if not _cooperative(dev):
        return (surfel_blend.blend_backward if backward else surfel_blend.blend_forward), 1
    fwd_block, bwd_block = _block_dims(s)
    if backward and warp_sums_kernel(dev, s, variant):
        block = min(s.tile_size**2, 256)
        return surfel_blend_gpu.backward_kernel_warp_sums(block, want.num_features, scatter=variant == "scatter"), block
    if backward:
        return surfel_blend_gpu.backward_kernel(bwd_block, _block_reduce(), want.num_features), bwd_block
    return surfel_blend_gpu.forward_kernel(fwd_block, want.num_features), fwd_block
