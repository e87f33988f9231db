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


def _scatter_snippet(width: int) -> str:
    """Native code of a reduce-scatter of `width` (16 or 32) values x over the warp, for a stub taking (x, lane).
    Each butterfly step halves the values a lane keeps: it adds its partner's copy of the half it keeps and hands
    over the other half, so the sums take width - 1 shuffles (plus one for 16) instead of width x 5, and every sum
    ends in its own lanes (value (lane >> 1) & 15 for 16, value lane for 32), which can then write their sums with
    one atomic instruction instead of lane 0 writing all of them in turn. Written out with constant indices: a loop
    over the halves left the values in local memory (the call 1.6x slower on an H200)."""
    lines, names, bit = [], [f"x[{i}]" for i in range(width)], 16
    while len(names) > 1:
        half = len(names) // 2
        new = [f"v{bit}_{i}" for i in range(half)]
        lines += [f"    const float {new[i]} = WPGS_KEEP({bit}, {names[i]}, {names[i + half]});" for i in range(half)]
        names, bit = new, bit // 2
    result = names[0] if bit == 0 else f"{names[0]} + __shfl_xor_sync(0xffffffffu, {names[0]}, 1)"
    shift = 0 if width == 32 else 1
    return f"""
#if defined(__CUDA_ARCH__)
    #define WPGS_KEEP(bit, lo, hi) (((lane & bit) != 0 ? (hi) : (lo)) + \\
        __shfl_xor_sync(0xffffffffu, (lane & bit) != 0 ? (lo) : (hi), bit))
{chr(10).join(lines)}
    #undef WPGS_KEEP
    return {result};
#else
    if constexpr (WP_TILE_BLOCK_DIM == 1) {{
        return x[0];
    }} else {{
        wp::wp_block_shared<float[WP_TILE_BLOCK_DIM * {width}]> scratch;
        const int t = WP_TILE_THREAD_IDX;
        WP_TILE_SYNC();
        for (int i = 0; i < {width}; ++i)
            (*scratch)[t * {width} + i] = x[i];
        WP_TILE_SYNC();
        const int first = t - t % 32;
        const int last = first + 32 < WP_TILE_BLOCK_DIM ? first + 32 : WP_TILE_BLOCK_DIM;
        const int k = (lane >> {shift}) & {width - 1};
        float v = 0.0f;
        for (int i = first; i < last; ++i)
            v += (*scratch)[i * {width} + k];
        WP_TILE_SYNC();
        return v;
    }}
#endif
"""


Lanes16 = wp.types.vector(length=16, dtype=float)  # what lane_scatter_sum takes
Lanes32 = wp.types.vector(length=32, dtype=float)  # what lane_scatter_sum32 takes


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


@wp.func_native(_scatter_snippet(16))
def lane_scatter_sum(x: Lanes16, lane: int) -> float:
    """The sum over the warp (32 lanes) of x[(lane >> 1) & 15], in lane `lane` (the caller's lane index, tid % 32):
    each of the 16 sums lands in two neighbouring lanes."""
    ...


@wp.func_native(_scatter_snippet(32))
def lane_scatter_sum32(x: Lanes32, lane: int) -> float:
    """The sum over the warp (32 lanes) of x[lane], in lane `lane` (the caller's lane index, tid % 32)."""
    ...


@wp.func
def lane_sum2(v: wp.vec2) -> wp.vec2:
    return wp.vec2(lane_sum(v[0]), lane_sum(v[1]))


@wp.func
def lane_sum3(v: wp.vec3) -> wp.vec3:
    return wp.vec3(lane_sum(v[0]), lane_sum(v[1]), lane_sum(v[2]))
