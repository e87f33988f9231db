"""Block-cooperative blending for GPUs: one block of tile_size² threads per tile.

The per-thread kernels in blend.py load each Gaussian of a tile's list one after another, so every step
waits on a dependent global load. Here the block fetches the list in batches of block_dim Gaussians into
shared memory (each thread gathers one), then every thread walks the batch from shared memory. The
forward stops a tile once all its pixels are saturated; the backward walks back to front in lockstep
from the block's largest stopping point and, optionally, sums each Gaussian's gradient over the block
before one thread adds it to global memory (`backward_kernel`), or, the default, each warp sums over its own
32 pixels with shuffles and skips what none of them blended (`backward_kernel_warp_sums`, at the end). The
per-pixel maths are blend.py's @wp.func's.

Kernels are compiled per block size (tile shapes are fixed at compile time) and per feature-channel count C:
features travel as length-C vectors (`feature_vector_type`), so a pixel accumulates them in registers and the
backward sums a Gaussian's feature gradient over the block in one vector reduction, instead of C global
read-modify-writes and C block reductions per blended Gaussian.
"""
import functools

import warp as wp

from .pair_sums import pair_part_index
from .warp_ops import Lanes16, lane_any, lane_max, lane_scatter_sum, lane_sum, lane_sum2, lane_sum3

from .blend import (
    ROW_USED,
    ROW_SUFFIX,
    ROW_T,
    ROW_WEIGHT,
    BlendParams,
    GradRow,
    add_gradient_row,
    mahalanobis,
    load_pixel_grads,
    new_pixel_state,
    pixel_gradient,
    seen_alpha,
    thread_pixel,
    write_pixel,
)


# What the block sums per Gaussian: the ten gradient entries of a GradRow, its "used" flag, and |d means2d| (AbsGS).
GradSum = wp.types.vector(length=13, dtype=float)


def feature_vector_type(num_features: int):
    """The vector type features are passed as for C channels (length 1, unused, when there are none)."""
    return _vector_type(max(int(num_features), 1))


@functools.lru_cache(maxsize=None)  # one type per length: kernels and the arrays passed to them must agree
def _vector_type(length: int):
    return wp.types.vector(length=length, dtype=float)


@wp.func
def gradient_sum_part(row: GradRow) -> GradSum:
    return GradSum(row[0], row[1], row[2], row[3], row[4], row[5], row[6], row[7], row[8], row[9], row[ROW_USED],
                   wp.abs(row[0]), wp.abs(row[1]))


@wp.func
def add_gradient_sum(g: int, total: GradSum, adj_means2d: wp.array(dtype=wp.vec2), adj_conics: wp.array(dtype=wp.vec3),
                     adj_opacities: wp.array(dtype=float), adj_colors: wp.array(dtype=wp.vec3),
                     adj_depths: wp.array(dtype=float), adj_means2d_abs: wp.array(dtype=wp.vec2), want_absgrad: int):
    wp.atomic_add(adj_means2d, g, wp.vec2(total[0], total[1]))
    wp.atomic_add(adj_conics, g, wp.vec3(total[2], total[3], total[4]))
    wp.atomic_add(adj_opacities, g, total[5])
    wp.atomic_add(adj_colors, g, wp.vec3(total[6], total[7], total[8]))
    wp.atomic_add(adj_depths, g, total[9])
    if want_absgrad != 0:
        wp.atomic_add(adj_means2d_abs, g, wp.vec2(total[11], total[12]))


@functools.lru_cache(maxsize=None)  # compiled once per block size and feature count
def forward_kernel(block_dim: int, num_features: int):
    FeatureVec = feature_vector_type(num_features)
    has_features = num_features > 0

    @wp.kernel(module="unique", module_options={"block_dim": block_dim, "enable_backward": False})
    def blend_forward_blocks(
        tile_start: wp.array(dtype=wp.int32),
        tile_end: wp.array(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        colors: wp.array(dtype=wp.vec3),
        depths: wp.array(dtype=float),
        features: wp.array(dtype=FeatureVec),
        q_cut: wp.array(dtype=float),
        p: BlendParams,
        out_color: wp.array(dtype=wp.vec3),
        out_transmittance: wp.array(dtype=float),
        out_alpha: wp.array(dtype=float),
        out_depth: wp.array(dtype=float),
        out_expected_depth: wp.array(dtype=float),
        out_inv_depth: wp.array(dtype=float),
        out_features: wp.array(dtype=FeatureVec),
        out_last: wp.array(dtype=wp.int32),
    ):
        inside, pix, tile, fx, fy = thread_pixel(wp.tid(), p)  # outside threads still help fetch
        start = tile_start[tile]
        end = tile_end[tile]
        st = new_pixel_state(start)
        acc = FeatureVec()
        if not inside:
            st.done = 1
        for b in range((end - start + wp.static(block_dim) - 1) / wp.static(block_dim)):
            if wp.tile_sum(wp.tile(1 - st.done))[0] == 0:  # every pixel of the tile is saturated
                break
            lo = start + b * wp.static(block_dim)
            ids = wp.tile_load(sorted_ids, shape=wp.static(block_dim), offset=lo, storage="shared")
            m_t = wp.tile_load_indexed(means2d, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            c_t = wp.tile_load_indexed(conics, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            o_t = wp.tile_load_indexed(opacities, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            q_t = wp.tile_load_indexed(q_cut, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            rgb_t = wp.tile_load_indexed(colors, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            z_t = wp.tile_load_indexed(depths, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            # A saturated pixel leaves the batch at once (breaking, not skipping the rest: 14-22% of the kernel's
            # time on an H200, in a side-by-side test of kernel variants); the block waits for its slowest pixel.
            for j in range(wp.where(st.done == 0, wp.min(wp.static(block_dim), end - lo), 0)):
                # blend_one written out: the state is updated in place and colour and depth leave shared memory
                # only for blended entries (14% of the kernel on an H200 against calling blend_one; same bits).
                mean = wp.tile_extract(m_t, j)
                dx = fx - mean[0]
                dy = fy - mean[1]
                q = mahalanobis(wp.tile_extract(c_t, j), dx, dy)
                if q <= wp.tile_extract(q_t, j):
                    alpha = wp.min(p.alpha_max, wp.tile_extract(o_t, j) * wp.exp(-0.5 * q))
                    if alpha >= p.alpha_min:
                        next_T = st.T * (1.0 - alpha)
                        if next_T < p.t_min:
                            st.done = 1
                            break
                        w = alpha * st.T
                        st.rgb = st.rgb + w * wp.tile_extract(rgb_t, j)  # loaded even when not wanted: harmless
                        z = wp.tile_extract(z_t, j)
                        st.depth = st.depth + w * z
                        if p.want_inv_depth != 0:
                            st.inv_depth = st.inv_depth + w / z
                        st.w = w
                        st.T = next_T
                        st.last = lo + j + 1
                if wp.static(has_features):
                    if st.last == lo + j + 1:
                        acc += st.w * features[wp.tile_extract(ids, j)]
        if inside:
            write_pixel(st, pix, p, out_color, out_transmittance, out_alpha, out_depth, out_expected_depth,
                        out_inv_depth, out_last)
            if wp.static(has_features):
                out_features[pix] = acc

    return blend_forward_blocks


@functools.lru_cache(maxsize=None)
def backward_kernel(block_dim: int, block_reduce: bool, num_features: int, deterministic: bool = False):
    """deterministic: each block's sums go to their own slot per sorted pair (pair_sums.py; needs block_reduce)."""
    if deterministic and not block_reduce:
        raise ValueError("the deterministic adjoint sums over the block: block_reduce must be on")
    FeatureVec = feature_vector_type(num_features)
    has_features = num_features > 0

    @wp.kernel(module="unique", module_options={"block_dim": block_dim, "enable_backward": False})
    def blend_backward_blocks(
        tile_start: wp.array(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        colors: wp.array(dtype=wp.vec3),
        depths: wp.array(dtype=float),
        features: wp.array(dtype=FeatureVec),
        q_cut: wp.array(dtype=float),
        p: BlendParams,
        transmittance: wp.array(dtype=float),
        last_index: wp.array(dtype=wp.int32),
        zacc: wp.array(dtype=float),  # the forward's depth accumulation (read when p.depth_eps > 0)
        grad_color: wp.array(dtype=wp.vec3),
        grad_alpha: wp.array(dtype=float),
        grad_depth: wp.array(dtype=float),
        grad_inv_depth: wp.array(dtype=float),
        grad_features: wp.array(dtype=FeatureVec),
        adj_means2d: wp.array(dtype=wp.vec2),
        adj_conics: wp.array(dtype=wp.vec3),
        adj_opacities: wp.array(dtype=float),
        adj_colors: wp.array(dtype=wp.vec3),
        adj_depths: wp.array(dtype=float),
        adj_features: wp.array(dtype=FeatureVec),
        adj_means2d_abs: wp.array(dtype=wp.vec2),  # written when p.want_absgrad (a placeholder otherwise)
    ):
        tid = wp.tid()
        lane = tid % wp.static(block_dim)
        inside, pix, tile, fx, fy = thread_pixel(tid, p)  # outside threads still help fetch and sum
        start = tile_start[tile]
        up = load_pixel_grads(pix, p, grad_color, grad_alpha, grad_depth, grad_inv_depth, transmittance, zacc)
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
            m_t = wp.tile_load_indexed(means2d, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            c_t = wp.tile_load_indexed(conics, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            o_t = wp.tile_load_indexed(opacities, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            q_t = wp.tile_load_indexed(q_cut, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            rgb_t = wp.tile_load_indexed(colors, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            z_t = wp.tile_load_indexed(depths, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            for step in range(hi - lo):
                j = hi - lo - 1 - step
                g = wp.tile_extract(ids, j)
                row = GradRow()
                if lo + j < last:
                    mean = wp.tile_extract(m_t, j)
                    conic = wp.tile_extract(c_t, j)
                    seen = seen_alpha(mean, conic, wp.tile_extract(o_t, j), wp.tile_extract(q_t, j), fx, fy, p)
                    if seen[0] > 0.0:
                        feature_dot = float(0.0)
                        if wp.static(has_features):
                            feature_dot = wp.dot(features[g], up_features)
                        row = pixel_gradient(mean, conic, seen, wp.tile_extract(rgb_t, j), wp.tile_extract(z_t, j),
                                             fx, fy, T, suffix, up, feature_dot, p)
                        T = row[ROW_T]
                        suffix = row[ROW_SUFFIX]
                if wp.static(block_reduce):
                    dest = g  # deterministic: this block's slot for the pair instead (pair_sums.py)
                    if wp.static(deterministic):
                        dest = pair_part_index(lo + j, tid, p.tile_size, wp.static(block_dim))
                    total = wp.tile_sum(wp.tile(gradient_sum_part(row), preserve_type=True))[0]
                    if lane == 0 and total[10] > 0.0:
                        add_gradient_sum(dest, total, adj_means2d, adj_conics, adj_opacities, adj_colors, adj_depths,
                                         adj_means2d_abs, p.want_absgrad)
                    if wp.static(has_features):
                        f_total = wp.tile_sum(wp.tile(row[ROW_WEIGHT] * up_features, preserve_type=True))[0]
                        if lane == 0 and total[10] > 0.0:
                            wp.atomic_add(adj_features, dest, f_total)
                else:
                    if row[ROW_USED] > 0.0:
                        add_gradient_row(g, row, adj_means2d, adj_conics, adj_opacities, adj_colors, adj_depths,
                                         adj_means2d_abs, p.want_absgrad)
                        if wp.static(has_features):
                            wp.atomic_add(adj_features, g, row[ROW_WEIGHT] * up_features)

    return blend_backward_blocks


# --- Pixel-per-thread adjoint with per-warp sums (the default on GPUs) --------------------------------------------
# `backward_kernel`'s layout (a thread per pixel, a block per tile or part of one, the list fetched in batches of
# block_dim Gaussians into shared memory), with each warp of the block on its own for everything else: it skips the
# entries past the last one any of its pixels blended, votes to skip Gaussians none of its pixels blended, sums the
# gradient over its 32 pixels with butterfly shuffles (warp_ops) that leave the sum in every lane, and adds it from
# lane 0. No shared memory and no block barrier per Gaussian: `backward_kernel` spends two barriers and a
# shared-memory broadcast on every Gaussian of the list, blended or not (its tile_sum()[0]).
# On an H100 (1M Gaussians, 1080p, tile 8) a whole fwd+bwd took 5.9 ms against 7.9 ms with `backward_kernel`
# (benchmarks/raster.py, side by side); under ncu the kernel took 3.6 ms against 5.8 ms, with the SMs 79% busy
# issuing (70-72 registers, 41% occupancy; `backward_kernel`: 90 registers, 29%), so fewer instructions per
# Gaussian is what would make it faster still. A reduce-scatter of the ten sums (16 shuffles instead of 50) and a
# one-warp-per-tile layout (two pixels a lane) timed the same or slower and were dropped. Blocks must be whole
# warps (tiles of 8x8 pixels and up).

WARP = 32


# Where the scatter adjoint adds a GradRow's entries (opacity, entry 5, goes to its own array): one flat float block
# holding means2d [N,2], conics [N,3], colors [N,3] and depths [N] one after another (fast_pipeline.blend_backward's
# fields, in that order); entry k of primitive g lands at offset * N + stride * g + component, SCATTER_LAYOUT[k].
SCATTER_LAYOUT = ((0, 2, 0), (0, 2, 1), (2, 3, 0), (2, 3, 1), (2, 3, 2), None, (5, 3, 0), (5, 3, 1), (5, 3, 2),
                  (8, 1, 0))


@wp.func
def scatter_slot(k: int, g: int, n: int) -> int:
    """SCATTER_LAYOUT's place of entry k (not 5) of primitive g, of n."""
    if k < 2:
        return 2 * g + k
    if k < 5:
        return 2 * n + 3 * g + k - 2
    if k < 9:
        return 5 * n + 3 * g + k - 6
    return 8 * n + g


def warp_sums_supported(tile_size: int) -> bool:
    return (tile_size * tile_size) % WARP == 0


@functools.lru_cache(maxsize=None)  # compiled once per block size and feature count
def backward_kernel_warp_sums(block_dim: int, num_features: int, deterministic: bool = False, absgrad: bool = False,
                              scatter: bool = False):
    """deterministic: each warp's sums go to their own slot per sorted pair (pair_sums.py), not to the primitive.
    absgrad: also sums each pixel's |d means2d| (AbsGS) into adj_means2d_abs; compiled in only when asked, so the
    default kernel carries none of it.
    scatter: the ten gradient sums of a Gaussian by one reduce-scatter (warp_ops.lane_scatter_sum), written by ten
    lanes at once into `adj_block` (laid out as SCATTER_LAYOUT says) and adj_opacities, instead of ten butterfly
    sums written by lane 0 (not with deterministic or absgrad)."""
    if block_dim % WARP != 0:
        raise ValueError(f"per-warp sums need whole warps per block, got block_dim={block_dim}")
    if scatter and (deterministic or absgrad):
        raise ValueError("the scatter sums write to the primitives' gradients: not with deterministic or absgrad")
    FeatureVec = feature_vector_type(num_features)
    has_features = num_features > 0

    @wp.kernel(module="unique", module_options={"block_dim": block_dim, "enable_backward": False})
    def blend_backward_warp_sums(
        tile_start: wp.array(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        colors: wp.array(dtype=wp.vec3),
        depths: wp.array(dtype=float),
        features: wp.array(dtype=FeatureVec),
        q_cut: wp.array(dtype=float),
        p: BlendParams,
        transmittance: wp.array(dtype=float),
        last_index: wp.array(dtype=wp.int32),
        zacc: wp.array(dtype=float),  # the forward's depth accumulation (read when p.depth_eps > 0)
        grad_color: wp.array(dtype=wp.vec3),
        grad_alpha: wp.array(dtype=float),
        grad_depth: wp.array(dtype=float),
        grad_inv_depth: wp.array(dtype=float),
        grad_features: wp.array(dtype=FeatureVec),
        adj_means2d: wp.array(dtype=wp.vec2),
        adj_conics: wp.array(dtype=wp.vec3),
        adj_opacities: wp.array(dtype=float),
        adj_colors: wp.array(dtype=wp.vec3),
        adj_depths: wp.array(dtype=float),
        adj_features: wp.array(dtype=FeatureVec),
        adj_means2d_abs: wp.array(dtype=wp.vec2),  # written when compiled with absgrad (a placeholder otherwise)
        adj_block: wp.array(dtype=float),  # written when compiled with scatter (a placeholder otherwise)
    ):
        tid = wp.tid()
        lane = tid % WARP
        inside, pix, tile, fx, fy = thread_pixel(tid, p)  # outside threads still help fetch and vote
        start = tile_start[tile]
        up = load_pixel_grads(pix, p, grad_color, grad_alpha, grad_depth, grad_inv_depth, transmittance, zacc)
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
            m_t = wp.tile_load_indexed(means2d, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            c_t = wp.tile_load_indexed(conics, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            o_t = wp.tile_load_indexed(opacities, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            q_t = wp.tile_load_indexed(q_cut, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            rgb_t = wp.tile_load_indexed(colors, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            z_t = wp.tile_load_indexed(depths, indices=ids, shape=(wp.static(block_dim),), offset=(0,), axis=0, storage="shared")
            for step in range(wp.min(hi, warp_last) - lo):  # this warp's entries only (uniform per warp)
                j = wp.min(hi, warp_last) - lo - 1 - step
                mean = wp.tile_extract(m_t, j)
                conic = wp.tile_extract(c_t, j)
                seen = wp.vec3(0.0)
                if lo + j < last:
                    seen = seen_alpha(mean, conic, wp.tile_extract(o_t, j), wp.tile_extract(q_t, j), fx, fy, p)
                blended = wp.where(seen[0] > 0.0, 1, 0)
                if lane_any(blended) != 0:  # some pixel of the warp blended it (uniform per warp)
                    g = wp.tile_extract(ids, j)
                    row = GradRow()
                    f_part = FeatureVec()
                    if blended != 0:
                        feature_dot = float(0.0)
                        if wp.static(has_features):
                            feature_dot = wp.dot(features[g], up_features)
                        row = pixel_gradient(mean, conic, seen, wp.tile_extract(rgb_t, j), wp.tile_extract(z_t, j),
                                             fx, fy, T, suffix, up, feature_dot, p)
                        T = row[ROW_T]
                        suffix = row[ROW_SUFFIX]
                        if wp.static(has_features):
                            f_part = row[ROW_WEIGHT] * up_features
                    dest = g  # deterministic: this warp's slot for the pair instead (pair_sums.py)
                    if wp.static(deterministic):
                        dest = pair_part_index(lo + j, tid, p.tile_size, WARP)
                    if wp.static(scatter):  # sum k of the row in lanes 2k and 2k + 1; the even ones write it
                        total = lane_scatter_sum(Lanes16(row[0], row[1], row[2], row[3], row[4], row[5], row[6],
                                                         row[7], row[8], row[9], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0), lane)
                        k = (lane >> 1) & 15
                        if (lane & 1) == 0 and k < 10:
                            if k == 5:
                                wp.atomic_add(adj_opacities, g, total)
                            else:
                                wp.atomic_add(adj_block, scatter_slot(k, g, adj_opacities.shape[0]), total)
                    else:
                        m = lane_sum2(wp.vec2(row[0], row[1]))
                        c = lane_sum3(wp.vec3(row[2], row[3], row[4]))
                        o = lane_sum(row[5])
                        col = lane_sum3(wp.vec3(row[6], row[7], row[8]))
                        d = lane_sum(row[9])
                        if lane == 0:  # one set of atomics per warp and Gaussian
                            wp.atomic_add(adj_means2d, dest, m)
                            wp.atomic_add(adj_conics, dest, c)
                            wp.atomic_add(adj_opacities, dest, o)
                            wp.atomic_add(adj_colors, dest, col)
                            wp.atomic_add(adj_depths, dest, d)
                        if wp.static(absgrad):  # each pixel's |d means2d|, summed (AbsGS)
                            m_abs = lane_sum2(wp.vec2(wp.abs(row[0]), wp.abs(row[1])))
                            if lane == 0:
                                wp.atomic_add(adj_means2d_abs, dest, m_abs)
                    if wp.static(has_features):
                        f_sum = FeatureVec()
                        for ch in range(wp.static(num_features)):
                            f_sum[ch] = lane_sum(f_part[ch])
                        if lane == 0:
                            wp.atomic_add(adj_features, dest, f_sum)

    return blend_backward_warp_sums
