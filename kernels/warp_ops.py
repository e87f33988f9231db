"""Warp-level collectives (32 lanes) for the blend kernels: native shuffles and votes on GPUs, and the same results
on the CPU's cooperative blocks (Warp's CPU fibers), where kernels run for tests.

Why native code: Warp's tile reductions (wp.tile_sum, ...) are block-wide and their results reach the other
threads only through shared memory and two block barriers, per call. These butterfly reductions leave the sum
in every lane with five shuffles and no barrier, and a vote is one instruction.

Rules for callers (as for CUDA's *_sync intrinsics with a full mask): every lane of the warp calls, with the same
control flow. On the CPU a call is a block-wide barrier, so there every thread of the block must call: the
kernels keep these calls on block-uniform paths when run on the CPU (`lane_any` answers for the whole block there,
which keeps branches taken on its answer uniform; the sums stay per 32-lane group, as on the GPU). The CPU branch
uses Warp 1.19's CPU tile runtime (wp_block_shared, WP_TILE_SYNC, WP_TILE_THREAD_IDX), the same that
wp.tile_from_thread uses; tests/test_raster_gpu_kernels_on_cpu.py runs every kernel that calls these.
"""
import warp as wp

_SUM = """
#if defined(__CUDA_ARCH__)
    float v = x;
    v += __shfl_xor_sync(0xffffffffu, v, 16);
    v += __shfl_xor_sync(0xffffffffu, v, 8);
    v += __shfl_xor_sync(0xffffffffu, v, 4);
    v += __shfl_xor_sync(0xffffffffu, v, 2);
    v += __shfl_xor_sync(0xffffffffu, v, 1);
    return v;
#else
    if constexpr (WP_TILE_BLOCK_DIM == 1) {
        return x;
    } else {
        wp::wp_block_shared<float[WP_TILE_BLOCK_DIM]> scratch;
        const int t = WP_TILE_THREAD_IDX;
        WP_TILE_SYNC();
        (*scratch)[t] = x;
        WP_TILE_SYNC();
        const int first = t - t % 32;
        const int last = first + 32 < WP_TILE_BLOCK_DIM ? first + 32 : WP_TILE_BLOCK_DIM;
        float v = 0.0f;
        for (int i = first; i < last; ++i)
            v += (*scratch)[i];
        WP_TILE_SYNC();
        return v;
    }
#endif
"""

_MAX_INT = """
#if defined(__CUDA_ARCH__)
    int v = x;
    v = max(v, __shfl_xor_sync(0xffffffffu, v, 16));
    v = max(v, __shfl_xor_sync(0xffffffffu, v, 8));
    v = max(v, __shfl_xor_sync(0xffffffffu, v, 4));
    v = max(v, __shfl_xor_sync(0xffffffffu, v, 2));
    v = max(v, __shfl_xor_sync(0xffffffffu, v, 1));
    return v;
#else
    if constexpr (WP_TILE_BLOCK_DIM == 1) {
        return x;
    } else {
        wp::wp_block_shared<int[WP_TILE_BLOCK_DIM]> scratch;
        const int t = WP_TILE_THREAD_IDX;
        WP_TILE_SYNC();
        (*scratch)[t] = x;
        WP_TILE_SYNC();
        int v = x;
        for (int i = 0; i < WP_TILE_BLOCK_DIM; ++i)  // block-wide on the CPU: keeps callers' branches uniform
            v = (*scratch)[i] > v ? (*scratch)[i] : v;
        WP_TILE_SYNC();
        return v;
    }
#endif
"""

_ANY = """
#if defined(__CUDA_ARCH__)
    return __any_sync(0xffffffffu, x != 0) ? 1 : 0;
#else
    if constexpr (WP_TILE_BLOCK_DIM == 1) {
        return x != 0 ? 1 : 0;
    } else {
        wp::wp_block_shared<int[WP_TILE_BLOCK_DIM]> scratch;
        const int t = WP_TILE_THREAD_IDX;
        WP_TILE_SYNC();
        (*scratch)[t] = x != 0 ? 1 : 0;
        WP_TILE_SYNC();
        int v = 0;
        for (int i = 0; i < WP_TILE_BLOCK_DIM; ++i)  // block-wide on the CPU: keeps callers' branches uniform
            v |= (*scratch)[i];
        WP_TILE_SYNC();
        return v;
    }
#endif
"""


# lane_scatter_sum: a reduce-scatter of 16 values over the warp. Each butterfly step halves the values a lane keeps:
# it adds its partner's copy of the half it keeps and hands over the other half, so 16 sums take 8+4+2+1+1 = 16
# shuffles instead of 16 x 5, and every sum ends in two lanes (lane L holds value (L >> 1) & 15), which can then
# write their sums with one atomic instruction instead of lane 0 writing all of them in turn.
_SCATTER_SUM = """
#if defined(__CUDA_ARCH__)
    // written out with constant indices: a loop over the halves left the values in local memory (1.6x slower)
    #define WPGS_KEEP(bit, lo, hi) (((lane & bit) != 0 ? (hi) : (lo)) + \
        __shfl_xor_sync(0xffffffffu, (lane & bit) != 0 ? (lo) : (hi), bit))
    const float a0 = WPGS_KEEP(16, x[0], x[8]), a1 = WPGS_KEEP(16, x[1], x[9]);
    const float a2 = WPGS_KEEP(16, x[2], x[10]), a3 = WPGS_KEEP(16, x[3], x[11]);
    const float a4 = WPGS_KEEP(16, x[4], x[12]), a5 = WPGS_KEEP(16, x[5], x[13]);
    const float a6 = WPGS_KEEP(16, x[6], x[14]), a7 = WPGS_KEEP(16, x[7], x[15]);
    const float b0 = WPGS_KEEP(8, a0, a4), b1 = WPGS_KEEP(8, a1, a5), b2 = WPGS_KEEP(8, a2, a6), b3 = WPGS_KEEP(8, a3, a7);
    const float c0 = WPGS_KEEP(4, b0, b2), c1 = WPGS_KEEP(4, b1, b3);
    const float d0 = WPGS_KEEP(2, c0, c1);
    #undef WPGS_KEEP
    return d0 + __shfl_xor_sync(0xffffffffu, d0, 1);
#else
    if constexpr (WP_TILE_BLOCK_DIM == 1) {
        return x[0];
    } else {
        wp::wp_block_shared<float[WP_TILE_BLOCK_DIM * 16]> scratch;
        const int t = WP_TILE_THREAD_IDX;
        WP_TILE_SYNC();
        for (int i = 0; i < 16; ++i)
            (*scratch)[t * 16 + i] = x[i];
        WP_TILE_SYNC();
        const int first = t - t % 32;
        const int last = first + 32 < WP_TILE_BLOCK_DIM ? first + 32 : WP_TILE_BLOCK_DIM;
        const int k = (lane >> 1) & 15;
        float v = 0.0f;
        for (int i = first; i < last; ++i)
            v += (*scratch)[i * 16 + k];
        WP_TILE_SYNC();
        return v;
    }
#endif
"""

Lanes16 = wp.types.vector(length=16, dtype=float)  # what lane_scatter_sum takes


@wp.func_native(_SUM)
def lane_sum(x: float) -> float:
    """The sum of x over the calling thread's warp (32 lanes), in every lane."""
    ...


@wp.func_native(_MAX_INT)
def lane_max(x: int) -> int:
    """The largest x of the warp on GPUs (of the whole block on the CPU), in every lane."""
    ...


@wp.func_native(_ANY)
def lane_any(x: int) -> int:
    """1 if x != 0 in any lane of the warp on GPUs (of the whole block on the CPU), in every lane."""
    ...


@wp.func_native(_SCATTER_SUM)
def lane_scatter_sum(x: Lanes16, lane: int) -> float:
    """The sum over the warp (32 lanes) of x[(lane >> 1) & 15], in lane `lane` (the caller's lane index, tid % 32):
    each of the 16 sums lands in two neighbouring lanes."""
    ...


@wp.func
def lane_sum2(v: wp.vec2) -> wp.vec2:
    return wp.vec2(lane_sum(v[0]), lane_sum(v[1]))


@wp.func
def lane_sum3(v: wp.vec3) -> wp.vec3:
    return wp.vec3(lane_sum(v[0]), lane_sum(v[1]), lane_sum(v[2]))
