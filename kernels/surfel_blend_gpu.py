"""Block-cooperative surfel blending for GPUs, as `blend_gpu.py` does it for 3D Gaussians.

The block fetches its tile's list in batches of block_dim surfels into shared memory (each thread gathers
one surfel's transform, centre, depth, opacity, cut-off, colour and normal), then every thread walks the batch
from shared memory. The forward stops a tile once all its pixels are saturated; the backward walks back to
front in lockstep from the block's largest stopping point and, optionally, sums each surfel's gradient over
the block before one thread adds it to global memory (`backward_kernel`), or each warp sums over its own 32 pixels
with shuffles and skips what none of them blended (`backward_kernel_warp_sums`, at the end; blend_gpu.py says why
that layout). The per-pixel maths are surfel_steps.py's @wp.func's.
Kernels are compiled per block size (tile shapes are fixed at compile time) and per feature-channel count:
features travel as length-C vectors, as in blend_gpu.
"""
import functools

import warp as wp

from .blend import thread_pixel
from .blend_gpu import WARP, feature_vector_type
from .pair_sums import pair_part_index
from .warp_ops import Lanes32, lane_any, lane_max, lane_scatter_sum32, lane_sum
from .surfel_steps import (
    ROW_COLOR,
    ROW_DEPTH,
    ROW_HIT,
    ROW_MEAN,
    ROW_NORMAL,
    ROW_OPACITY,
    ROW_SCREEN,
    ROW_SUFFIX,
    ROW_T,
    ROW_WEIGHT,
    SplatPoint,
    SurfelBlendParams,
    SurfelGradRow,
    add_surfel_gradient_row,
    blend_alpha,
    blend_surfel,
    load_pixel_grads,
    new_surfel_state,
    saturates,
    splat_point,
    surfel_pixel_gradient,
    write_surfel_pixel,
)


# What the block sums per surfel: the gradient entries of a SurfelGradRow and its hit / screen flags, which
# then count the pixels that took each path (add_surfel_gradient_row reads them the same way).
GRAD_SUM_LENGTH = ROW_SCREEN + 1  # entries 0 .. ROW_SCREEN of a row
SurfelGradSum = wp.types.vector(length=GRAD_SUM_LENGTH, dtype=float)


@wp.func
def gradient_sum_part(row: SurfelGradRow) -> SurfelGradSum:
    part = SurfelGradSum()
    for i in range(wp.static(GRAD_SUM_LENGTH)):
        part[i] = row[i]
    return part


@wp.func
def gradient_sum_row(total: SurfelGradSum) -> SurfelGradRow:
    row = SurfelGradRow()
    for i in range(wp.static(GRAD_SUM_LENGTH)):
        row[i] = total[i]
    return row


@functools.lru_cache(maxsize=None)  # compiled once per block size and feature count
def forward_kernel(block_dim: int, num_features: int):
    FeatureVec = feature_vector_type(num_features)
    has_features = num_features > 0

    @wp.kernel(module="unique", module_options={"block_dim": block_dim, "enable_backward": False})
    def surfel_blend_forward_blocks(
        tile_start: wp.array(dtype=wp.int32),
        tile_end: wp.array(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        transforms: wp.array(dtype=wp.mat33),
        means2d: wp.array(dtype=wp.vec2),
        depths: wp.array(dtype=float),
        opacities: wp.array(dtype=float),
        colors: wp.array(dtype=wp.vec3),
        normals: wp.array(dtype=wp.vec3),
        features: wp.array(dtype=FeatureVec),
        q_cut: wp.array(dtype=float),
        p: SurfelBlendParams,
        out_color: wp.array(dtype=wp.vec3),
        out_transmittance: wp.array(dtype=float),
        out_alpha: wp.array(dtype=float),
        out_depth: wp.array(dtype=float),
        out_expected_depth: wp.array(dtype=float),
        out_inv_depth: wp.array(dtype=float),
        out_normal: wp.array(dtype=wp.vec3),
        out_median: wp.array(dtype=float),
        out_median_index: wp.array(dtype=wp.int32),
        out_distortion: wp.array(dtype=float),
        out_dist_stats: wp.array(dtype=wp.vec3),
        out_features: wp.array(dtype=FeatureVec),
        out_last: wp.array(dtype=wp.int32),
    ):
        inside, pix, tile, fx, fy = thread_pixel(wp.tid(), p.base)  # outside threads still help fetch
        start = tile_start[tile]
        end = tile_end[tile]
        st = new_surfel_state(start)
        acc = FeatureVec()
        done = wp.where(inside, 0, 1)  # 1 once the pixel is saturated
        for b in range((end - start + wp.static(block_dim) - 1) / wp.static(block_dim)):
            if wp.tile_sum(wp.tile(1 - done))[0] == 0:  # every pixel of the tile is saturated
                break
            lo = start + b * wp.static(block_dim)
            ids = wp.tile_load(sorted_ids, shape=wp.static(block_dim), offset=lo, storage="shared")
            M_t = wp.tile_load_indexed(transforms, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            m_t = wp.tile_load_indexed(means2d, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            z_t = wp.tile_load_indexed(depths, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            o_t = wp.tile_load_indexed(opacities, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            q_t = wp.tile_load_indexed(q_cut, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            rgb_t = wp.tile_load_indexed(colors, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            n_t = wp.tile_load_indexed(normals, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            # Saturated pixels walk nothing; the others stop when they saturate (the steps as in surfel_blend's
            # per-thread kernel: skip decisions first, then the straight-line blend).
            for j in range(wp.where(done == 0, wp.min(wp.static(block_dim), end - lo), 0)):
                sp = splat_point(wp.tile_extract(M_t, j), wp.tile_extract(m_t, j), wp.tile_extract(z_t, j), fx, fy,
                                 p.near, p.filter_inv)
                if sp[0] > wp.tile_extract(q_t, j):
                    continue
                alpha = blend_alpha(wp.tile_extract(o_t, j), wp.exp(-0.5 * sp[0]), p.base.alpha_max)
                if alpha < p.base.alpha_min:
                    continue
                if saturates(st.T, alpha, p.base.t_min):
                    done = 1
                    break
                if wp.static(has_features):
                    acc += alpha * st.T * features[wp.tile_extract(ids, j)]
                st = blend_surfel(st, lo + j, alpha, sp[1], wp.tile_extract(rgb_t, j), wp.tile_extract(n_t, j), p)
        if inside:
            write_surfel_pixel(st, pix, p, out_color, out_transmittance, out_alpha, out_depth, out_expected_depth,
                               out_inv_depth, out_normal, out_median, out_median_index, out_distortion,
                               out_dist_stats, out_last)
            if wp.static(has_features):
                out_features[pix] = acc

    return surfel_blend_forward_blocks


@functools.lru_cache(maxsize=None)
def backward_kernel(block_dim: int, block_reduce: bool, num_features: int, deterministic: bool = False):
    """deterministic: each block's sums go to their own slot per sorted pair (pair_sums.py; needs block_reduce)."""
    if deterministic and not block_reduce:
        raise ValueError("the deterministic adjoint sums over the block: block_reduce must be on")
    FeatureVec = feature_vector_type(num_features)
    has_features = num_features > 0

    @wp.kernel(module="unique", module_options={"block_dim": block_dim, "enable_backward": False})
    def surfel_blend_backward_blocks(
        tile_start: wp.array(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        transforms: wp.array(dtype=wp.mat33),
        means2d: wp.array(dtype=wp.vec2),
        depths: wp.array(dtype=float),
        opacities: wp.array(dtype=float),
        colors: wp.array(dtype=wp.vec3),
        normals: wp.array(dtype=wp.vec3),
        features: wp.array(dtype=FeatureVec),
        q_cut: wp.array(dtype=float),
        p: SurfelBlendParams,
        transmittance: wp.array(dtype=float),
        last_index: wp.array(dtype=wp.int32),
        median_index: wp.array(dtype=wp.int32),
        dist_stats: wp.array(dtype=wp.vec3),
        zacc: wp.array(dtype=float),  # the forward's depth accumulation (read when p.base.depth_eps > 0)
        grad_color: wp.array(dtype=wp.vec3),
        grad_alpha: wp.array(dtype=float),
        grad_depth: wp.array(dtype=float),
        grad_inv_depth: wp.array(dtype=float),
        grad_normal: wp.array(dtype=wp.vec3),
        grad_median: wp.array(dtype=float),
        grad_distortion: wp.array(dtype=float),
        grad_features: wp.array(dtype=FeatureVec),
        adj_transforms: wp.array(dtype=wp.mat33),
        adj_means2d: wp.array(dtype=wp.vec2),
        adj_depths: wp.array(dtype=float),
        adj_opacities: wp.array(dtype=float),
        adj_colors: wp.array(dtype=wp.vec3),
        adj_normals: wp.array(dtype=wp.vec3),
        adj_features: wp.array(dtype=FeatureVec),
    ):
        tid = wp.tid()
        lane = tid % wp.static(block_dim)
        inside, pix, tile, fx, fy = thread_pixel(tid, p.base)  # outside threads still help fetch and sum
        start = tile_start[tile]
        pg = load_pixel_grads(pix, p, transmittance, median_index, dist_stats, zacc, grad_color, grad_alpha,
                              grad_depth, grad_inv_depth, grad_normal, grad_median, grad_distortion)
        up_features = FeatureVec()
        if wp.static(has_features):
            up_features = grad_features[pix]
        T = transmittance[pix]
        suffix = float(0.0)
        last = wp.where(inside, last_index[pix], start)
        block_last = wp.tile_max(wp.tile(last))[0]
        for b in range((block_last - start + wp.static(block_dim) - 1) / wp.static(block_dim)):
            hi = block_last - b * wp.static(block_dim)
            lo = wp.max(start, hi - wp.static(block_dim))
            ids = wp.tile_load(sorted_ids, shape=wp.static(block_dim), offset=lo, storage="shared")
            M_t = wp.tile_load_indexed(transforms, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            m_t = wp.tile_load_indexed(means2d, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            z_t = wp.tile_load_indexed(depths, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            o_t = wp.tile_load_indexed(opacities, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            q_t = wp.tile_load_indexed(q_cut, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            rgb_t = wp.tile_load_indexed(colors, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            n_t = wp.tile_load_indexed(normals, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            for step in range(hi - lo):
                j = hi - lo - 1 - step
                g = wp.tile_extract(ids, j)
                row = SurfelGradRow()
                if lo + j < last:
                    M = wp.tile_extract(M_t, j)
                    mean = wp.tile_extract(m_t, j)
                    sp = splat_point(M, mean, wp.tile_extract(z_t, j), fx, fy, p.near, p.filter_inv)
                    if not (sp[0] > wp.tile_extract(q_t, j)):  # the tests of the per-thread kernel, negated
                        G = wp.exp(-0.5 * sp[0])
                        o = wp.tile_extract(o_t, j)
                        if not (blend_alpha(o, G, p.base.alpha_max) < p.base.alpha_min):
                            feature_dot = float(0.0)
                            if wp.static(has_features):
                                feature_dot = wp.dot(features[g], up_features)
                            row = surfel_pixel_gradient(lo + j, sp, M, mean, o, G, wp.tile_extract(rgb_t, j),
                                                        wp.tile_extract(n_t, j), fx, fy, T, suffix, pg, feature_dot,
                                                        p)
                            T = row[ROW_T]
                            suffix = row[ROW_SUFFIX]
                if wp.static(block_reduce):
                    dest = g  # deterministic: this block's slot for the pair instead (pair_sums.py)
                    if wp.static(deterministic):
                        dest = pair_part_index(lo + j, tid, p.base.tile_size, wp.static(block_dim))
                    total = wp.tile_sum(wp.tile(gradient_sum_part(row), preserve_type=True))[0]
                    used = total[ROW_HIT] + total[ROW_SCREEN] > 0.0
                    if lane == 0 and used:
                        add_surfel_gradient_row(dest, gradient_sum_row(total), p,
                                                adj_transforms, adj_means2d, adj_depths, adj_opacities, adj_colors,
                                                adj_normals)
                    if wp.static(has_features):
                        f_total = wp.tile_sum(wp.tile(row[ROW_WEIGHT] * up_features, preserve_type=True))[0]
                        if lane == 0 and used:
                            wp.atomic_add(adj_features, dest, f_total)
                else:
                    if row[ROW_HIT] + row[ROW_SCREEN] > 0.0:
                        add_surfel_gradient_row(g, row, p, adj_transforms, adj_means2d,
                                                adj_depths, adj_opacities, adj_colors, adj_normals)
                        if wp.static(has_features):
                            wp.atomic_add(adj_features, g, row[ROW_WEIGHT] * up_features)

    return surfel_blend_backward_blocks


# --- Pixel-per-thread adjoint with per-warp sums ----------------------------------------------------------------
# blend_gpu.backward_kernel_warp_sums's layout for surfels: each warp skips the entries past the last one any of its
# pixels blended, votes to skip surfels none of its pixels blended, and sums a surfel's GRAD_SUM_LENGTH gradient
# entries over its 32 pixels with butterfly shuffles before lane 0 adds them (or, with `scatter`, with one
# reduce-scatter that leaves entry k's sum in lane k, and the lanes add theirs at once); no block barrier per surfel.
# On an H200 it took fwd+bwd from 5.2 to 3.2 ms (100k surfels) and from 19.0 to 9.6 ms (1M) at 1080p against
# `backward_kernel` (benchmarks/raster.py --primitive surfels); the scatter (raster option surfel_backward_kernel,
# the default) 3.51 -> 3.13 ms and 9.84 -> 9.35 ms against lane 0's sums.


# Where the scatter adjoint adds a SurfelGradRow's entries (opacity, ROW_OPACITY, goes to its own array; the hit and
# screen counts are not written): one flat float block holding transforms [N,9], means2d [N,2], depths [N], colors
# [N,3] and normals [N,3] one after another (fast_pipeline_surfels.ADJOINT_FIELDS, in that order); entry k of surfel g
# lands at offset * N + stride * g + component, SCATTER_LAYOUT[k].
SCATTER_LAYOUT = tuple([(0, 9, c) for c in range(9)] + [(9, 2, 0), (9, 2, 1), (11, 1, 0), None]
                       + [(12, 3, c) for c in range(3)] + [(15, 3, c) for c in range(3)])


@wp.func
def scatter_slot(k: int, g: int, n: int) -> int:
    """SCATTER_LAYOUT's place of entry k (below ROW_HIT, not ROW_OPACITY) of surfel g, of n."""
    if k < ROW_MEAN:
        return 9 * g + k
    if k < ROW_DEPTH:
        return 9 * n + 2 * g + k - ROW_MEAN
    if k == ROW_DEPTH:
        return 11 * n + g
    if k < ROW_NORMAL:
        return 12 * n + 3 * g + k - ROW_COLOR
    return 15 * n + 3 * g + k - ROW_NORMAL


@functools.lru_cache(maxsize=None)  # compiled once per block size and feature count
def backward_kernel_warp_sums(block_dim: int, num_features: int, deterministic: bool = False, scatter: bool = False):
    """deterministic: each warp's sums go to their own slot per sorted pair (pair_sums.py), not to the surfel.
    scatter: a surfel's gradient entries summed by one 32-value reduce-scatter (warp_ops.lane_scatter_sum32), lane k
    writing entry k into `adj_block` (laid out as SCATTER_LAYOUT says) or adj_opacities, instead of
    GRAD_SUM_LENGTH butterfly sums written by lane 0 (not with deterministic)."""
    if block_dim % WARP != 0:
        raise ValueError(f"per-warp sums need whole warps per block, got block_dim={block_dim}")
    if scatter and deterministic:
        raise ValueError("the scatter sums write to the surfels' gradients: not with deterministic")
    FeatureVec = feature_vector_type(num_features)
    has_features = num_features > 0

    # max_unroll: the per-entry sums are unrolled (GRAD_SUM_LENGTH > Warp's default of 16)
    @wp.kernel(module="unique", module_options={"block_dim": block_dim, "enable_backward": False, "max_unroll": 32})
    def surfel_blend_backward_warp_sums(
        tile_start: wp.array(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        transforms: wp.array(dtype=wp.mat33),
        means2d: wp.array(dtype=wp.vec2),
        depths: wp.array(dtype=float),
        opacities: wp.array(dtype=float),
        colors: wp.array(dtype=wp.vec3),
        normals: wp.array(dtype=wp.vec3),
        features: wp.array(dtype=FeatureVec),
        q_cut: wp.array(dtype=float),
        p: SurfelBlendParams,
        transmittance: wp.array(dtype=float),
        last_index: wp.array(dtype=wp.int32),
        median_index: wp.array(dtype=wp.int32),
        dist_stats: wp.array(dtype=wp.vec3),
        zacc: wp.array(dtype=float),  # the forward's depth accumulation (read when p.base.depth_eps > 0)
        grad_color: wp.array(dtype=wp.vec3),
        grad_alpha: wp.array(dtype=float),
        grad_depth: wp.array(dtype=float),
        grad_inv_depth: wp.array(dtype=float),
        grad_normal: wp.array(dtype=wp.vec3),
        grad_median: wp.array(dtype=float),
        grad_distortion: wp.array(dtype=float),
        grad_features: wp.array(dtype=FeatureVec),
        adj_transforms: wp.array(dtype=wp.mat33),
        adj_means2d: wp.array(dtype=wp.vec2),
        adj_depths: wp.array(dtype=float),
        adj_opacities: wp.array(dtype=float),
        adj_colors: wp.array(dtype=wp.vec3),
        adj_normals: wp.array(dtype=wp.vec3),
        adj_features: wp.array(dtype=FeatureVec),
        adj_block: wp.array(dtype=float),  # written when compiled with scatter (a placeholder otherwise)
    ):
        tid = wp.tid()
        lane = tid % WARP
        inside, pix, tile, fx, fy = thread_pixel(tid, p.base)  # outside threads still help fetch and vote
        start = tile_start[tile]
        pg = load_pixel_grads(pix, p, transmittance, median_index, dist_stats, zacc, grad_color, grad_alpha,
                              grad_depth, grad_inv_depth, grad_normal, grad_median, grad_distortion)
        up_features = FeatureVec()
        if wp.static(has_features):
            up_features = grad_features[pix]
        T = transmittance[pix]
        suffix = float(0.0)
        last = wp.where(inside, last_index[pix], start)
        block_last = wp.tile_max(wp.tile(last))[0]
        warp_last = lane_max(last)
        for b in range((block_last - start + wp.static(block_dim) - 1) / wp.static(block_dim)):
            hi = block_last - b * wp.static(block_dim)
            lo = wp.max(start, hi - wp.static(block_dim))
            ids = wp.tile_load(sorted_ids, shape=wp.static(block_dim), offset=lo, storage="shared")
            M_t = wp.tile_load_indexed(transforms, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            m_t = wp.tile_load_indexed(means2d, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            z_t = wp.tile_load_indexed(depths, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            o_t = wp.tile_load_indexed(opacities, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            q_t = wp.tile_load_indexed(q_cut, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            rgb_t = wp.tile_load_indexed(colors, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            n_t = wp.tile_load_indexed(normals, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            for step in range(wp.min(hi, warp_last) - lo):  # this warp's entries only (uniform per warp)
                j = wp.min(hi, warp_last) - lo - 1 - step
                M = wp.tile_extract(M_t, j)
                mean = wp.tile_extract(m_t, j)
                o = wp.tile_extract(o_t, j)
                sp = SplatPoint()
                G = float(0.0)
                blended = int(0)
                if lo + j < last:  # the tests of the per-thread kernel
                    sp = splat_point(M, mean, wp.tile_extract(z_t, j), fx, fy, p.near, p.filter_inv)
                    if not (sp[0] > wp.tile_extract(q_t, j)):
                        G = wp.exp(-0.5 * sp[0])
                        if not (blend_alpha(o, G, p.base.alpha_max) < p.base.alpha_min):
                            blended = 1
                if lane_any(blended) != 0:  # some pixel of the warp blended it (uniform per warp)
                    g = wp.tile_extract(ids, j)
                    row = SurfelGradRow()
                    f_part = FeatureVec()
                    if blended != 0:
                        feature_dot = float(0.0)
                        if wp.static(has_features):
                            feature_dot = wp.dot(features[g], up_features)
                        row = surfel_pixel_gradient(lo + j, sp, M, mean, o, G, wp.tile_extract(rgb_t, j),
                                                    wp.tile_extract(n_t, j), fx, fy, T, suffix, pg, feature_dot, p)
                        T = row[ROW_T]
                        suffix = row[ROW_SUFFIX]
                        if wp.static(has_features):
                            f_part = row[ROW_WEIGHT] * up_features
                    dest = g  # deterministic: this warp's slot for the pair instead (pair_sums.py)
                    if wp.static(deterministic):
                        dest = pair_part_index(lo + j, tid, p.base.tile_size, WARP)
                    if wp.static(scatter):  # entry k's sum in lane k; a zero sum (a path no pixel took) is skipped
                        part = Lanes32()
                        for i in range(wp.static(GRAD_SUM_LENGTH)):
                            part[i] = row[i]
                        total_k = lane_scatter_sum32(part, lane)
                        if lane < ROW_HIT and total_k != 0.0:
                            if lane == ROW_OPACITY:
                                wp.atomic_add(adj_opacities, g, total_k)
                            else:
                                wp.atomic_add(adj_block, scatter_slot(lane, g, adj_opacities.shape[0]), total_k)
                    else:
                        total = SurfelGradSum()
                        for i in range(wp.static(GRAD_SUM_LENGTH)):
                            total[i] = lane_sum(row[i])
                        if lane == 0:  # one set of atomics per warp and surfel
                            add_surfel_gradient_row(dest, gradient_sum_row(total), p, adj_transforms, adj_means2d,
                                                    adj_depths, adj_opacities, adj_colors, adj_normals)
                    if wp.static(has_features):
                        f_sum = FeatureVec()
                        for ch in range(wp.static(num_features)):
                            f_sum[ch] = lane_sum(f_part[ch])
                        if lane == 0:
                            wp.atomic_add(adj_features, dest, f_sum)

    return surfel_blend_backward_warp_sums
