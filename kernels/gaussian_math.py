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
def symmetric2_inverse(a: float, b: float, c: float) -> wp.vec3:
    """Inverse of [[a, b], [b, c]] (positive definite) as (a', b', c'), scaled to avoid float32 overflow."""
    s = wp.max(wp.max(a, c), 1.0e-12)
    an = a / s
    bn = b / s
    cn = c / s
    det = wp.max(an * cn - bn * bn, 1.0e-30)
    k = 1.0 / (det * s)
    return wp.vec3(cn * k, -bn * k, an * k)


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
