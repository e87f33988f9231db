"""Packed splat rows (the layout model-parallel ranks exchange, `warpgs/render/splats_fast.py`) into the contiguous
per-field arrays the blend kernels read: the GPU kernels' tile loads of a batch of splats address contiguous arrays,
so strided views of the rows' columns would read the wrong memory there. One launch for all six fields."""
import warp as wp

# The row layout, field: (first column, width); features follow from column SPLAT_COLUMNS on (read in place).
LAYOUT = {"means2d": (0, 2), "conics": (2, 3), "cov2d": (5, 3), "depths": (8, 1), "colors": (9, 3),
          "opacities": (12, 1)}
SPLAT_COLUMNS = 13
MEANS2D, CONICS, COV2D, DEPTHS, COLORS, OPACITIES = (wp.constant(LAYOUT[name][0]) for name in LAYOUT)


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
    means2d[i] = wp.vec2(rows[i, MEANS2D], rows[i, MEANS2D + 1])
    conics[i] = wp.vec3(rows[i, CONICS], rows[i, CONICS + 1], rows[i, CONICS + 2])
    cov2d[i] = wp.vec3(rows[i, COV2D], rows[i, COV2D + 1], rows[i, COV2D + 2])
    depths[i] = rows[i, DEPTHS]
    colors[i] = wp.vec3(rows[i, COLORS], rows[i, COLORS + 1], rows[i, COLORS + 2])
    opacities[i] = rows[i, OPACITIES]
