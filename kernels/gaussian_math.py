"""Small differentiable helpers shared by the projection kernels (quaternions, 2x2 inverses, gradient tests)."""
import warp as wp

# Largest |scale| we feed into the covariance: beyond it a Gaussian already covers the whole screen
# with constant alpha, and larger values would overflow float32 in the projected covariance.
MAX_SCALE = wp.constant(1.0e8)


@wp.func
def quat_wxyz_to_rotation(q: wp.vec4) -> wp.mat33:
    """Rotation of an unnormalised wxyz quaternion; the zero quaternion maps to the identity."""
    # max() keeps sqrt's adjoint finite for q = 0 (the rotation formula below then gives the identity).
    inv_norm = 1.0 / wp.sqrt(wp.max(wp.dot(q, q), 1.0e-24))
    w = q[0] * inv_norm
    x = q[1] * inv_norm
    y = q[2] * inv_norm
    z = q[3] * inv_norm
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )


@wp.func
def clamp_scale(s: float) -> float:
    return wp.clamp(s, -MAX_SCALE, MAX_SCALE)


@wp.func
def covariance_det_scaled(t0: wp.vec3, t1: wp.vec3, low_pass: float, s: float) -> float:
    """det([[t0.t0 + lp, t0.t1], [t0.t1, t1.t1 + lp]]) / s^2, written as the Lagrange identity |t0 x t1|^2 +
    lp (|t0|^2 + |t1|^2) + lp^2 on the rows scaled by 1/sqrt(s): no cancellation, where a c - b^2 of a long, thin
    footprint (a needle seen side on: 3e7 px^2 along it, the 0.3 px^2 low-pass across) is float32 noise."""
    r = 1.0 / wp.sqrt(s)
    u0 = t0 * r
    u1 = t1 * r
    lp = low_pass / s
    x = wp.cross(u0, u1)
    return wp.dot(x, x) + lp * (wp.dot(u0, u0) + wp.dot(u1, u1)) + lp * lp


@wp.func
def covariance_inverse(t0: wp.vec3, t1: wp.vec3, low_pass: float, a: float, b: float, c: float) -> wp.vec3:
    """Inverse of the 2D covariance [[a, b], [b, c]] = T T^T + low_pass I (t0, t1: T's rows) as (a', b', c'),
    scaled to avoid float32 overflow, its determinant from covariance_det_scaled."""
    s = wp.max(wp.max(a, c), 1.0e-12)
    det = wp.max(covariance_det_scaled(t0, t1, low_pass, s), 1.0e-30)
    k = 1.0 / (det * s)
    return wp.vec3(c / s * k, -b / s * k, a / s * k)


@wp.func
def rotation_of(viewmat: wp.mat44) -> wp.mat33:
    return wp.mat33(
        viewmat[0, 0], viewmat[0, 1], viewmat[0, 2],
        viewmat[1, 0], viewmat[1, 1], viewmat[1, 2],
        viewmat[2, 0], viewmat[2, 1], viewmat[2, 2],
    )


@wp.func
def translation_of(viewmat: wp.mat44) -> wp.vec3:
    return wp.vec3(viewmat[0, 3], viewmat[1, 3], viewmat[2, 3])


@wp.func
def nonzero2(v: wp.vec2) -> bool:
    """Any component non-zero (NaN counts: a NaN gradient still propagates)."""
    return v[0] != 0.0 or v[1] != 0.0


@wp.func
def nonzero3(v: wp.vec3) -> bool:
    """Any component non-zero (NaN counts: a NaN gradient still propagates)."""
    return v[0] != 0.0 or v[1] != 0.0 or v[2] != 0.0
