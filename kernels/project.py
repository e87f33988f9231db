"""Per-Gaussian stage: camera transform, EWA projection with the 0.3 px² low-pass, view-dependent colour.

Written branch-free so that Warp's generated adjoint is exact: culled Gaussians still compute guarded,
finite values (they receive a zero adjoint because they never reach a tile).
"""
import warp as wp

from .gaussian_math import (clamp_scale, covariance_inverse, nonzero2, nonzero3, quat_wxyz_to_rotation, rotation_of,
                            translation_of)
from .sh import colour_from_sh, eval_sh

# The low-pass, in px², added to the projected covariance (3DGS and gsplat's eps2d: 0.3) is the `low_pass` argument.
COLOR_DIRECT = wp.constant(0)
COLOR_SH = wp.constant(1)


@wp.func
def view_bounds(width: int, height: int, intr: wp.vec4) -> wp.vec4:
    """(lo_x, hi_x, lo_y, hi_y): the limits of x/z and y/z in the EWA Jacobian, 1.3x the field of view as in 3DGS
    (keeps far off-screen Gaussians from producing huge footprints). intr: (fx, fy, cx, cy)."""
    tan_x = 0.5 * float(width) / intr[0]
    tan_y = 0.5 * float(height) / intr[1]
    return wp.vec4(-(intr[2] / intr[0] + 0.3 * tan_x), (float(width) - intr[2]) / intr[0] + 0.3 * tan_x,
                   -(intr[3] / intr[1] + 0.3 * tan_y), (float(height) - intr[3]) / intr[1] + 0.3 * tan_y)


@wp.func
def project_one(
    i: int,
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    coeffs: wp.array2d(dtype=wp.vec3),  # [N, K]: K=1 plain colours, K>=(d+1)^2 SH
    viewmat: wp.array(dtype=wp.mat44),  # [1] or [N] world -> camera (OpenCV)
    intrinsics: wp.array(dtype=wp.vec4),  # [1] or [N] (fx, fy, cx, cy)
    width: int,
    height: int,
    near: float,
    far: float,
    color_mode: int,
    sh_degree: int,
    low_pass: float,  # px² added to the projected covariance's diagonal
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    cov2d: wp.array(dtype=wp.vec3),
    depths: wp.array(dtype=float),
    colors: wp.array(dtype=wp.vec3),
    valid: wp.array(dtype=wp.int32),
):
    """Projects Gaussian i (the body of both kernels below)."""
    # One camera, or one copy per Gaussian (the adjoint with camera gradients: each adds into its own row, not all
    # into one matrix with atomics; render/camera_rows.py)
    V = viewmat[wp.min(i, viewmat.shape[0] - 1)]
    R = rotation_of(V)
    t = translation_of(V)
    intr = intrinsics[wp.min(i, intrinsics.shape[0] - 1)]
    fx = intr[0]
    fy = intr[1]
    cx = intr[2]
    cy = intr[3]

    mu = means[i]
    p = R * mu + t
    z = p[2]
    zs = wp.max(z, near)  # guarded depth: finite maths for culled Gaussians

    # EWA Jacobian, x/z and y/z clamped (view_bounds)
    bounds = view_bounds(width, height, intr)
    xz = wp.clamp(p[0] / zs, bounds[0], bounds[1])
    yz = wp.clamp(p[1] / zs, bounds[2], bounds[3])
    J = wp.mat33(fx / zs, 0.0, -fx * xz / zs, 0.0, fy / zs, -fy * yz / zs, 0.0, 0.0, 0.0)

    s = scales[i]
    Rq = quat_wxyz_to_rotation(quats[i])
    M = Rq * wp.diag(wp.vec3(clamp_scale(s[0]), clamp_scale(s[1]), clamp_scale(s[2])))
    T = J * R * M
    t0 = wp.vec3(T[0, 0], T[0, 1], T[0, 2])
    t1 = wp.vec3(T[1, 0], T[1, 1], T[1, 2])
    a = wp.dot(t0, t0) + low_pass
    b = wp.dot(t0, t1)
    c = wp.dot(t1, t1) + low_pass

    means2d[i] = wp.vec2(fx * p[0] / zs + cx, fy * p[1] / zs + cy)
    conics[i] = covariance_inverse(t0, t1, low_pass, a, b, c)
    cov2d[i] = wp.vec3(a, b, c)
    depths[i] = zs

    if color_mode == COLOR_SH:
        campos = -(wp.transpose(R) * t)
        d = mu - campos
        d = d / wp.sqrt(wp.max(wp.dot(d, d), 1.0e-24))
        colors[i] = colour_from_sh(eval_sh(coeffs, i, sh_degree, d))
    else:
        colors[i] = coeffs[i, 0]

    ok = z >= near and z <= far and wp.isfinite(a) and wp.isfinite(c)
    valid[i] = wp.where(ok, 1, 0)


@wp.kernel
def project_gaussians(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    coeffs: wp.array2d(dtype=wp.vec3),  # [N, K]: K=1 plain colours, K>=(d+1)^2 SH
    viewmat: wp.array(dtype=wp.mat44),  # [1] or [N] world -> camera (OpenCV)
    intrinsics: wp.array(dtype=wp.vec4),  # [1] or [N] (fx, fy, cx, cy)
    width: int,
    height: int,
    near: float,
    far: float,
    color_mode: int,
    sh_degree: int,
    low_pass: float,  # px² added to the projected covariance's diagonal
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    cov2d: wp.array(dtype=wp.vec3),
    depths: wp.array(dtype=float),
    colors: wp.array(dtype=wp.vec3),
    valid: wp.array(dtype=wp.int32),
):
    project_one(wp.tid(), means, quats, scales, coeffs, viewmat, intrinsics, width, height, near, far, color_mode,
                sh_degree, low_pass, means2d, conics, cov2d, depths, colors, valid)


@wp.func
def reached(g_means2d: wp.vec2, g_conics: wp.vec3, g_colors: wp.vec3, g_depth: float) -> bool:
    """Whether a Gaussian has any upstream gradient (NaN counts as one, so it still propagates)."""
    return nonzero2(g_means2d) or nonzero3(g_conics) or nonzero3(g_colors) or g_depth != 0.0


@wp.kernel
def project_gaussians_reached(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    coeffs: wp.array2d(dtype=wp.vec3),  # [N, K]: K=1 plain colours, K>=(d+1)^2 SH
    viewmat: wp.array(dtype=wp.mat44),  # [1] or [N] world -> camera (OpenCV)
    intrinsics: wp.array(dtype=wp.vec4),  # [1] or [N] (fx, fy, cx, cy)
    width: int,
    height: int,
    near: float,
    far: float,
    color_mode: int,
    sh_degree: int,
    low_pass: float,  # px² added to the projected covariance's diagonal
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    cov2d: wp.array(dtype=wp.vec3),
    depths: wp.array(dtype=float),
    colors: wp.array(dtype=wp.vec3),
    valid: wp.array(dtype=wp.int32),
    g_means2d: wp.array(dtype=wp.vec2),  # upstream gradients of the outputs (read only)
    g_conics: wp.array(dtype=wp.vec3),
    g_colors: wp.array(dtype=wp.vec3),
    g_depths: wp.array(dtype=float),
):
    """project_gaussians for the Gaussians with an upstream gradient only. Its generated adjoint is the projection's
    adjoint: a Gaussian that reached no pixel (culled, off screen, behind the camera: often most of a 360° scene)
    has a zero adjoint, so it skips the replay and the 16 SH rows' gradient writes instead of computing zeros."""
    i = wp.tid()
    if reached(g_means2d[i], g_conics[i], g_colors[i], g_depths[i]):
        project_one(i, means, quats, scales, coeffs, viewmat, intrinsics, width, height, near, far, color_mode,
                    sh_degree, low_pass, means2d, conics, cov2d, depths, colors, valid)
