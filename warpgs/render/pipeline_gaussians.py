"""The rasterization pipeline on Warp arrays, per call: project -> bin into tiles -> sort -> blend, and the blend
adjoint, each stage allocating its own arrays (a wp.Tape can record the projection). The tests' oracles
(tests/legacy_raster*.py) run it; the render ops (whole and split, `splats_fast.py`) run `fast_pipeline`, which
takes its settings, block sizes and tile chunks from here.

Torch-free: the callers convert tensors and drive these stages.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import List, Tuple

import warp as wp

wp.config.log_level = wp.LOG_WARNING  # no banner or per-module load messages
# Read once: Warp's CPU blocks are switched on here, at import, so the choice cannot change later in the process.
_CPU_COOPERATIVE = os.environ.get("WARPGS_CPU_COOPERATIVE") == "1"
if _CPU_COOPERATIVE:
    wp.config.enable_cpu_blocks = True

from warpgs.render.cpu_threads import cpu_threads, run_threads, tile_ranges_per_thread  # noqa: E402
from warpgs.render.defaults import (DEFAULT_ALPHA_MAX, DEFAULT_ALPHA_MIN, DEFAULT_LOW_PASS,  # noqa: E402
                                    DEFAULT_SURFEL_SCREEN_SIGMA, DEFAULT_TILE_SIZE, DEFAULT_TRANSMITTANCE_MIN)
from warpgs.kernels import binning, blend, blend_gpu, project  # noqa: E402  (after setting the log level)


@dataclass
class Settings:
    width: int
    height: int
    near: float = 0.01
    far: float = 1e10
    tile_size: int = DEFAULT_TILE_SIZE
    max_sigmas: float = 0.0  # 0: exact footprint (everything with alpha >= alpha_min)
    sh_degree: int = -1  # -1: plain colours
    alpha_min: float = DEFAULT_ALPHA_MIN  # blending skips contributions below this alpha (3DGS: 1/255)
    transmittance_min: float = DEFAULT_TRANSMITTANCE_MIN  # blending stops before transmittance drops under this
    alpha_max: float = DEFAULT_ALPHA_MAX  # alpha is clamped here (3DGS: 0.99, gsplat: 0.999)
    screen_sigma: float = DEFAULT_SURFEL_SCREEN_SIGMA  # surfels: the screen-space fallback's sigma in pixels
    low_pass: float = DEFAULT_LOW_PASS  # 3D Gaussians: px² added to the projected covariance (3DGS, gsplat eps2d)

    @property
    def tiles_x(self) -> int:
        return (self.width + self.tile_size - 1) // self.tile_size

    @property
    def tiles_y(self) -> int:
        return (self.height + self.tile_size - 1) // self.tile_size

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y


@dataclass
class Projected:
    means2d: wp.array
    conics: wp.array
    cov2d: wp.array
    depths: wp.array
    colors: wp.array
    valid: wp.array


@dataclass
class Bins:
    tile_start: wp.array
    tile_end: wp.array
    sorted_ids: wp.array
    num_intersections: int
    counts: wp.array  # tiles touched per Gaussian (0: culled)
    q_cut: wp.array  # per Gaussian: largest Mahalanobis distance that can still be blended


@dataclass
class Wanted:
    color: bool
    depth: bool
    inv_depth: bool
    num_features: int
    absgrad: bool = False  # 3D adjoints: also sum each pixel's |d means2d| per Gaussian (AbsGS densification)


@dataclass
class Blended:
    color: wp.array
    transmittance: wp.array
    alpha: wp.array
    depth: wp.array
    inv_depth: wp.array
    features: wp.array
    last: wp.array


def project_gaussians(means, quats, scales, opacities, coeffs, viewmat, intrinsics, s: Settings, requires_grad: bool):
    n = means.shape[0]
    dev = means.device
    out = Projected(
        means2d=wp.zeros(n, dtype=wp.vec2, device=dev, requires_grad=requires_grad),
        conics=wp.zeros(n, dtype=wp.vec3, device=dev, requires_grad=requires_grad),
        cov2d=wp.empty(n, dtype=wp.vec3, device=dev),  # every output is written for every Gaussian
        depths=wp.zeros(n, dtype=float, device=dev, requires_grad=requires_grad),
        colors=wp.zeros(n, dtype=wp.vec3, device=dev, requires_grad=requires_grad),
        valid=wp.empty(n, dtype=wp.int32, device=dev),
    )
    color_mode = projection_color_mode(s)
    wp.launch(
        project.project_gaussians,
        dim=n,
        inputs=[means, quats, scales, coeffs, viewmat, intrinsics, s.width, s.height, s.near, s.far,
                color_mode, max(s.sh_degree, 0), s.low_pass],
        outputs=[out.means2d, out.conics, out.cov2d, out.depths, out.colors, out.valid],
        device=dev,
    )
    return out


def bin_gaussians(p: Projected, opacities, s: Settings) -> Bins:
    """Tiles touched by each projected 3D Gaussian (exact alpha >= alpha_min footprint), then `sort_into_tiles`."""
    return bin_into_tiles(binning.tile_footprints, [p.means2d, p.cov2d, opacities, p.valid], p.depths, s)


def bin_into_tiles(footprint_kernel, footprint_inputs, depths, s: Settings) -> Bins:
    """Every primitive kind's binning, per call (tile_binning.bin_into_tiles is the workspace twin): its footprint
    kernel (inputs `footprint_inputs`, then the image and blend settings; it writes every primitive's tile
    rectangle, tile count and cut-off), then `sort_into_tiles`."""
    n = depths.shape[0]
    dev = depths.device
    counts = wp.empty(n, dtype=wp.int32, device=dev)  # written for every primitive
    rects = wp.empty(n, dtype=wp.vec4i, device=dev)
    q_cut = wp.empty(n, dtype=float, device=dev)
    wp.launch(footprint_kernel, dim=n,
              inputs=list(footprint_inputs) + [s.width, s.height, s.tile_size, s.max_sigmas, s.alpha_min],
              outputs=[rects, counts, q_cut], device=dev)
    return sort_into_tiles(rects, counts, depths, q_cut, s)


def sort_into_tiles(rects, counts, depths, q_cut, s: Settings) -> Bins:
    """Shared by every primitive kind: each primitive's tile rectangle as (tile, primitive) pairs sorted by tile,
    then depth, and each tile's [start, end) range in the sorted list. `depths` must be positive float32.
    Two stable radix sorts (see kernels/binning.py): the primitives by depth, then their pairs by tile index."""
    n = counts.shape[0]
    dev = counts.device
    total = 0
    tile_start = wp.zeros(s.num_tiles, dtype=wp.int32, device=dev)
    tile_end = wp.zeros(s.num_tiles, dtype=wp.int32, device=dev)
    if n > 0:
        depth_keys = wp.empty(2 * n, dtype=wp.int32, device=dev)  # radix sorts need 2x room
        order = wp.empty(2 * n, dtype=wp.int32, device=dev)
        wp.launch(binning.depth_sort_keys, dim=n, inputs=[depths.view(wp.int32)], outputs=[depth_keys, order],
                  device=dev)
        wp.utils.radix_sort_pairs(depth_keys, order, n)
        ordered_counts = wp.empty(n, dtype=wp.int32, device=dev)
        wp.launch(binning.counts_in_order, dim=n, inputs=[order, counts], outputs=[ordered_counts], device=dev)
        offsets = wp.empty(n, dtype=wp.int32, device=dev)
        wp.utils.array_scan(ordered_counts, offsets, inclusive=True)
        total = int(offsets[n - 1 : n].numpy()[0])  # the one host sync: sizes the pair buffers
    keys = wp.empty(2 * max(total, 1), dtype=wp.int32, device=dev)
    values = wp.empty(2 * max(total, 1), dtype=wp.int32, device=dev)
    if total > 0:
        if dev.is_cpu:  # a loop per primitive: few threads, no search
            wp.launch(binning.emit_tile_keys, dim=n, inputs=[rects, order, offsets, counts, s.tiles_x],
                      outputs=[keys, values], device=dev)
        else:  # a thread per (primitive, tile) pair: balanced across the GPU
            wp.launch(binning.emit_tile_keys_per_pair, dim=total, inputs=[rects, order, offsets, counts, s.tiles_x, n],
                      outputs=[keys, values], device=dev)
        tile_bits = max(1, (s.num_tiles - 1).bit_length())
        wp.utils.radix_sort_pairs(keys, values, total, begin_bit=0, end_bit=tile_bits)
        wp.launch(binning.tile_ranges, dim=total, inputs=[keys, total], outputs=[tile_start, tile_end], device=dev)
    return Bins(tile_start, tile_end, values[: max(total, 1)], total, counts, q_cut)


def _blend_inputs(p: Projected, bins: Bins, opacities, features):
    return [p.means2d, p.conics, opacities, p.colors, p.depths, features, bins.q_cut]


def projection_color_mode(s: Settings) -> int:
    """The projection kernels' colour mode: SH coefficients when the settings carry an SH degree, else plain colours."""
    return project.COLOR_SH if s.sh_degree >= 0 else project.COLOR_DIRECT


def blend_params(s: Settings, want: Wanted, first_tile: int = 0, depth_eps: float = 0.0) -> blend.BlendParams:
    """The per-launch settings every blend kernel takes (3D and surfel, CPU and GPU, forward and backward).
    depth_eps > 0: the 3D forward also writes the expected depth (accumulation / max(alpha, depth_eps))."""
    bp = blend.BlendParams()
    bp.width, bp.height, bp.tiles_x, bp.tile_size, bp.first_tile = s.width, s.height, s.tiles_x, s.tile_size, first_tile
    bp.want_color, bp.want_depth, bp.want_inv_depth = int(want.color), int(want.depth), int(want.inv_depth)
    bp.num_features = want.num_features
    bp.alpha_min, bp.t_min, bp.alpha_max = s.alpha_min, s.transmittance_min, s.alpha_max
    bp.depth_eps = float(depth_eps)
    bp.want_absgrad = int(want.absgrad)
    return bp


def _tile_launches(s: Settings, device) -> List[List[Tuple[int, int]]]:
    """(first_tile, count) chunks per worker: one launch on a GPU, several threads on the CPU."""
    if _cooperative(device):
        return [[(0, s.num_tiles)]]
    return tile_ranges_per_thread(s.num_tiles, cpu_threads())


def _cooperative(device) -> bool:
    """Block-cooperative kernels (blend_gpu.py) on GPUs. WARPGS_CPU_COOPERATIVE=1 runs them on the CPU too,
    with Warp's CPU blocks (fibers), so their maths can be tested without a GPU."""
    return _CPU_COOPERATIVE or not device.is_cpu


def _block_dims(s: Settings) -> Tuple[int, int]:
    """Threads per block of the cooperative forward and backward: consecutive pixels of one tile.
    Defaults: a whole tile for the forward (one shared fetch per batch), one warp for the backward (its
    per-Gaussian sums then need no block-wide synchronisation). WARPGS_FWD_BLOCK / WARPGS_BWD_BLOCK override."""
    per_tile = s.tile_size**2
    # At most 256: a 32x32 tile as one 1024-thread block asks for more registers than a GPU block has.
    fwd = int(os.environ.get("WARPGS_FWD_BLOCK", min(per_tile, 256)))
    bwd = int(os.environ.get("WARPGS_BWD_BLOCK", 32))
    return math.gcd(per_tile, fwd), math.gcd(per_tile, bwd)


def _block_reduce() -> bool:
    """Sum each Gaussian's gradient over the block before the atomics (WARPGS_BLOCK_REDUCE=0 turns it off)."""
    return os.environ.get("WARPGS_BLOCK_REDUCE", "1") != "0"


def blend_forward(p: Projected, bins: Bins, opacities, features, s: Settings, want: Wanted) -> Blended:
    dev = p.means2d.device
    npix = s.width * s.height
    out = Blended(
        # every pixel is written (empty), except the features, which are accumulated (zeros)
        color=wp.empty(npix if want.color else 1, dtype=wp.vec3, device=dev),
        transmittance=wp.empty(npix, dtype=float, device=dev),
        alpha=wp.empty(npix, dtype=float, device=dev),
        depth=wp.empty(npix if want.depth else 1, dtype=float, device=dev),
        inv_depth=wp.empty(npix if want.inv_depth else 1, dtype=float, device=dev),
        features=wp.zeros((npix, want.num_features) if want.num_features else (1, 1), dtype=float, device=dev),
        last=wp.empty(npix, dtype=wp.int32, device=dev),
    )
    kernel, block_dim, kernel_features = choose_blend_kernel(dev, s, want.num_features, blend.blend_forward,
                                                             blend_gpu, backward=False)
    features, out_features = kernel_features(features), kernel_features(out.features)
    head = [bins.tile_start, bins.tile_end, bins.sorted_ids] + _blend_inputs(p, bins, opacities, features)
    unused = wp.empty(1, dtype=float, device=dev)  # the expected depth: the torch op divides itself here

    def work(_thread, chunks):  # each chunk writes only its own pixels
        for first, count in chunks:
            wp.launch(kernel, dim=count * s.tile_size**2, inputs=head + [blend_params(s, want, first)],
                      outputs=[out.color, out.transmittance, out.alpha, out.depth, unused, out.inv_depth,
                               out_features, out.last], device=dev, block_dim=block_dim)

    run_threads(work, _tile_launches(s, dev), kernels=[kernel], device=dev, block_dim=block_dim)
    return out


def blend_backward(p: Projected, bins: Bins, opacities, features, s: Settings, want: Wanted, fwd: Blended,
                   grad_color, grad_alpha, grad_depth, grad_inv_depth, grad_features):
    """Accumulates into the .grad of means2d, conics, colors, depths (projected), opacities and features.

    CPU threads would race on those sums (Warp's CPU atomics are plain adds), so every thread but the first
    accumulates into private buffers that are added in afterwards."""
    dev = p.means2d.device
    kernel, block_dim, kernel_features = choose_blend_kernel(dev, s, want.num_features, blend.blend_backward,
                                                             blend_gpu, backward=True)
    features, grad_features, adj_features = (kernel_features(a) for a in (features, grad_features, features.grad))
    targets = [p.means2d.grad, p.conics.grad, opacities.grad, p.colors.grad, p.depths.grad, adj_features]
    head = [bins.tile_start, bins.sorted_ids] + _blend_inputs(p, bins, opacities, features)
    unused = wp.empty(1, dtype=float, device=dev)  # the depth accumulation: torch divides here
    tail = [fwd.transmittance, fwd.last, unused, grad_color, grad_alpha, grad_depth, grad_inv_depth, grad_features]
    per_thread = _tile_launches(s, dev)
    buffers = _gradient_buffers(targets, len(per_thread))
    no_absgrad = wp.zeros(1, dtype=wp.vec2, device=dev)  # this oracle path never asks for it

    def work(thread, chunks):
        for first, count in chunks:
            wp.launch(kernel, dim=count * s.tile_size**2,
                      inputs=head + [blend_params(s, want, first)] + tail + buffers[thread] + [no_absgrad],
                      device=dev, block_dim=block_dim)

    run_threads(work, per_thread, kernels=[kernel], device=dev, block_dim=block_dim)
    _merge_gradient_buffers(buffers)


def choose_blend_kernel(device, s: Settings, num_features: int, per_thread_kernel, cooperative_kernels,
                        backward: bool):
    """(kernel, block_dim, kernel_features) for a blend launch: on the CPU the per-thread kernel, one thread per
    block, features as [rows, C] arrays; on GPUs the block-cooperative kernel of `cooperative_kernels`
    (blend_gpu or surfel_blend_gpu) compiled for this block size and feature count, features as length-C
    vectors. kernel_features converts a features array (inputs, outputs or gradients) for the kernel."""
    if not _cooperative(device):
        return per_thread_kernel, 1, (lambda a: a)
    fwd_block, bwd_block = _block_dims(s)
    if backward:
        kernel = cooperative_kernels.backward_kernel(bwd_block, _block_reduce(), num_features)
    else:
        kernel = cooperative_kernels.forward_kernel(fwd_block, num_features)
    return kernel, (bwd_block if backward else fwd_block), (lambda a: feature_vectors(a, num_features))


def feature_vectors(a, num_features: int):
    """A contiguous [rows, C] float array seen, without a copy, as `rows` length-C vectors: the layout of the
    cooperative kernels' features (a 1-element dummy when there are no features)."""
    vec = blend_gpu.feature_vector_type(num_features)
    if num_features == 0 or a.shape[0] == 0:
        return wp.zeros(1, dtype=vec, device=a.device)
    if not (a.ndim == 2 and a.shape[1] == num_features and a.is_contiguous):
        raise ValueError(f"features: expected a contiguous [rows, {num_features}] array, got shape {a.shape}"
                         f"{'' if a.is_contiguous else ' (not contiguous)'}")
    return wp.array(ptr=a.ptr, dtype=vec, shape=(a.shape[0],), device=a.device)


def _gradient_buffers(targets, threads: int):
    """Per thread, where its blend adjoint accumulates: the targets for the first, private zeros for the rest."""
    return [targets] + [[wp.zeros_like(t) for t in targets] for _ in range(threads - 1)]


def _merge_gradient_buffers(buffers) -> None:
    """Adds the private buffers of `_gradient_buffers` into the targets (buffers[0])."""
    for private in buffers[1:]:
        for dst, src in zip(buffers[0], private):
            if dst.size == 0:
                continue
            flat_dst, flat_src = _as_flat_floats(dst), _as_flat_floats(src)
            wp.launch(blend.accumulate, dim=flat_dst.shape[0], inputs=[flat_src], outputs=[flat_dst],
                      device=dst.device)


def _as_flat_floats(a):
    return a.view(wp.float32).flatten() if a.dtype != wp.float32 else a.flatten()
