"""The render op's finite-value checks as one kernel, so that a GPU render needs no host sync of its own for them:
the kernel raises flags in a device array that the host reads with the tile-pair count, at the sync the pipeline
makes anyway (warpgs/render/fast_pipeline.py).

Every input is seen as a flat float array with a row width: per-primitive rows (means 3, quats 4, scales 3 or 2,
opacities 1, colours K*3, features C) are checked by thread i, the per-call ones (viewmat 16, K 9, background 3) by
thread 0. A width of 0 skips an array (e.g. no features). Writers only ever store 1, so races between threads are
harmless; the host zeroes the flags before each launch.
"""
import warp as wp

FLAG_SLOTS = 10  # one per checked array (ROW_ARGS then CALL_ARGS), then "an opacity outside [0, 1]"
OPACITY_RANGE_SLOT = 9


@wp.func
def row_has_nonfinite(a: wp.array(dtype=float), row: int, width: int) -> int:
    bad = int(0)
    for j in range(width):
        if not wp.isfinite(a[row * width + j]):
            bad = 1
    return bad


@wp.kernel
def flag_bad_inputs(
    means: wp.array(dtype=float),
    quats: wp.array(dtype=float),
    scales: wp.array(dtype=float),
    opacities: wp.array(dtype=float),
    colors: wp.array(dtype=float),
    features: wp.array(dtype=float),
    viewmat: wp.array(dtype=float),
    K: wp.array(dtype=float),
    background: wp.array(dtype=float),
    scale_width: int,  # 3 (2 for surfels)
    color_width: int,  # 3 * coefficients per primitive
    feature_width: int,  # 0 for none
    background_width: int,  # 3, or 0 for none
    flags: wp.array(dtype=wp.int32),  # [FLAG_SLOTS], zeroed by the caller
):
    i = wp.tid()
    if row_has_nonfinite(means, i, 3) != 0:
        flags[0] = 1
    if row_has_nonfinite(quats, i, 4) != 0:
        flags[1] = 1
    if row_has_nonfinite(scales, i, scale_width) != 0:
        flags[2] = 1
    o = opacities[i]
    if not wp.isfinite(o):
        flags[3] = 1
    elif o < 0.0 or o > 1.0:
        flags[OPACITY_RANGE_SLOT] = 1
    if row_has_nonfinite(colors, i, color_width) != 0:
        flags[4] = 1
    if row_has_nonfinite(features, i, feature_width) != 0:
        flags[5] = 1
    if i == 0:
        if row_has_nonfinite(viewmat, 0, 16) != 0:
            flags[6] = 1
        if row_has_nonfinite(K, 0, 9) != 0:
            flags[7] = 1
        if row_has_nonfinite(background, 0, background_width) != 0:
            flags[8] = 1
