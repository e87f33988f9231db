"""Packed splat rows (the layout model-parallel ranks exchange, `warpgs/render/splats_fast.py`) into the contiguous
per-field arrays the blend kernels read: the GPU kernels' tile loads of a batch of splats address contiguous arrays,
so strided views of the rows' columns would read the wrong memory there. One launch for all six fields.
Row layout: means2d 2, conic 3, cov2d 3, depth 1, colour 3, opacity 1 (then features, read in place)."""
import warp as wp


@wp.kernel
def unpack_splat_rows(
    rows: wp.array2d(dtype=float),
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    cov2d: wp.array(dtype=wp.vec3),
    depths: wp.array(dtype=float),
    colors: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
):
    i = wp.tid()
    means2d[i] = wp.vec2(rows[i, 0], rows[i, 1])
    conics[i] = wp.vec3(rows[i, 2], rows[i, 3], rows[i, 4])
    cov2d[i] = wp.vec3(rows[i, 5], rows[i, 6], rows[i, 7])
    depths[i] = rows[i, 8]
    colors[i] = wp.vec3(rows[i, 9], rows[i, 10], rows[i, 11])
    opacities[i] = rows[i, 12]
