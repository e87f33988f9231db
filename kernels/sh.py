"""Real spherical harmonics up to degree 3, evaluated along a unit view direction (3DGS band order)."""
import warp as wp

SH_C0 = wp.constant(0.28209479177387814)
SH_C1 = wp.constant(0.4886025119029199)
SH_C2_0 = wp.constant(1.0925484305920792)
SH_C2_1 = wp.constant(-1.0925484305920792)
SH_C2_2 = wp.constant(0.31539156525252005)
SH_C2_3 = wp.constant(-1.0925484305920792)
SH_C2_4 = wp.constant(0.5462742152960396)
SH_C3_0 = wp.constant(-0.5900435899266435)
SH_C3_1 = wp.constant(2.890611442640554)
SH_C3_2 = wp.constant(-0.4570457994644658)
SH_C3_3 = wp.constant(0.3731763325901154)
SH_C3_4 = wp.constant(-0.4570457994644658)
SH_C3_5 = wp.constant(1.445305721320277)
SH_C3_6 = wp.constant(-0.5900435899266435)


@wp.func
def eval_sh(coeffs: wp.array2d(dtype=wp.vec3), i: int, degree: int, d: wp.vec3) -> wp.vec3:
    """Σ_lm Y_lm(d) c_lm over bands 0..degree; bands above `degree` are never read."""
    result = SH_C0 * coeffs[i, 0]
    if degree > 0:
        x = d[0]
        y = d[1]
        z = d[2]
        result = result - SH_C1 * y * coeffs[i, 1] + SH_C1 * z * coeffs[i, 2] - SH_C1 * x * coeffs[i, 3]
        if degree > 1:
            xx = x * x
            yy = y * y
            zz = z * z
            result = (
                result
                + SH_C2_0 * (x * y) * coeffs[i, 4]
                + SH_C2_1 * (y * z) * coeffs[i, 5]
                + SH_C2_2 * (2.0 * zz - xx - yy) * coeffs[i, 6]
                + SH_C2_3 * (x * z) * coeffs[i, 7]
                + SH_C2_4 * (xx - yy) * coeffs[i, 8]
            )
            if degree > 2:
                result = (
                    result
                    + SH_C3_0 * y * (3.0 * xx - yy) * coeffs[i, 9]
                    + SH_C3_1 * (x * y * z) * coeffs[i, 10]
                    + SH_C3_2 * y * (4.0 * zz - xx - yy) * coeffs[i, 11]
                    + SH_C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * coeffs[i, 12]
                    + SH_C3_4 * x * (4.0 * zz - xx - yy) * coeffs[i, 13]
                    + SH_C3_5 * z * (xx - yy) * coeffs[i, 14]
                    + SH_C3_6 * x * (xx - 3.0 * yy) * coeffs[i, 15]
                )
    return result


@wp.func
def colour_from_sh(rgb: wp.vec3) -> wp.vec3:
    """SH value + 0.5, clamped at 0 per channel, with the derivative torch.clamp_min (and so gsplat and the 3DGS
    reference) gives: 1 where the value is >= 0, boundary included. wp.max would send a value of exactly 0 the
    constant's derivative, and a colour initialised at exactly 0 (a black SfM point: sh0 = -0.5 / C0) would then
    never get a gradient, nor would its split and cloned children."""
    c = rgb + wp.vec3(0.5, 0.5, 0.5)
    return wp.vec3(wp.where(c[0] >= 0.0, c[0], 0.0), wp.where(c[1] >= 0.0, c[1], 0.0),
                   wp.where(c[2] >= 0.0, c[2], 0.0))
