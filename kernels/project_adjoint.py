"""The 3D projection's adjoint written out (kernels/project.py's `project_one` run backwards), for the common
training case: one camera that is not differentiated (the renderer's default there; raster option project_adjoint).
Warp's generated adjoint, which serves the other cases, replays the forward, stores its outputs again and adds every
input gradient with an atomic; this one recomputes only what the chain rule needs and writes each Gaussian's
gradients once. Every min/max/clamp routes its gradient the way Warp's generated adjoint does (to the operand the
forward picked), so the two agree on every input, culled and clamped Gaussians included (tests/test_project_adjoint.py).
"""
import warp as wp

from .gaussian_math import MAX_SCALE, covariance_det_scaled, quat_wxyz_to_rotation, rotation_of, translation_of
from .project import COLOR_SH, view_bounds
from .sh import (SH_C0, SH_C1, eval_sh, SH_C2_0, SH_C2_1, SH_C2_2, SH_C2_3, SH_C2_4, SH_C3_0, SH_C3_1, SH_C3_2, SH_C3_3,
                 SH_C3_4, SH_C3_5, SH_C3_6)

# Which gradient arrays are real (a bit each); the others are 1-element placeholders never written.
WANT_MEANS = wp.constant(1)
WANT_QUATS = wp.constant(2)
WANT_SCALES = wp.constant(4)
WANT_COEFFS = wp.constant(8)


@wp.func
def passes_clamp(x: float, lo: float, hi: float) -> float:
    """1 where Warp's clamp adjoint hands the gradient to x (lo <= x < hi), else 0."""
    return wp.where(x >= lo and wp.max(lo, x) < hi, 1.0, 0.0)


@wp.func
def finite_or_zero3(v: wp.vec3) -> wp.vec3:
    return wp.vec3(wp.where(wp.isfinite(v[0]), v[0], 0.0), wp.where(wp.isfinite(v[1]), v[1], 0.0),
                   wp.where(wp.isfinite(v[2]), v[2], 0.0))


@wp.func
def finite_or_zero4(v: wp.vec4) -> wp.vec4:
    return wp.vec4(wp.where(wp.isfinite(v[0]), v[0], 0.0), wp.where(wp.isfinite(v[1]), v[1], 0.0),
                   wp.where(wp.isfinite(v[2]), v[2], 0.0), wp.where(wp.isfinite(v[3]), v[3], 0.0))


@wp.func
def quat_rotation_adjoint(q: wp.vec4, g: wp.mat33) -> wp.vec4:
    """Gradient of quat_wxyz_to_rotation(q) (normalised inside, guarded at 0) given the rotation's gradient g."""
    n2 = wp.dot(q, q)
    inv_norm = 1.0 / wp.sqrt(wp.max(n2, 1.0e-24))
    w = q[0] * inv_norm
    x = q[1] * inv_norm
    y = q[2] * inv_norm
    z = q[3] * inv_norm
    gw = 2.0 * (-z * g[0, 1] + y * g[0, 2] + z * g[1, 0] - x * g[1, 2] - y * g[2, 0] + x * g[2, 1])
    gx = 2.0 * (y * g[0, 1] + z * g[0, 2] + y * g[1, 0] - 2.0 * x * g[1, 1] - w * g[1, 2] + z * g[2, 0]
                + w * g[2, 1] - 2.0 * x * g[2, 2])
    gy = 2.0 * (-2.0 * y * g[0, 0] + x * g[0, 1] + w * g[0, 2] + x * g[1, 0] + z * g[1, 2] - w * g[2, 0]
                + z * g[2, 1] - 2.0 * y * g[2, 2])
    gz = 2.0 * (-2.0 * z * g[0, 0] - w * g[0, 1] + x * g[0, 2] + w * g[1, 0] - 2.0 * z * g[1, 1] + y * g[1, 2]
                + x * g[2, 0] + y * g[2, 1])
    g_unit = wp.vec4(gw, gx, gy, gz)
    g_q = g_unit * inv_norm
    if n2 > 1.0e-24:  # the normalisation's own derivative (none where the guard holds it constant)
        g_q = g_q - q * (wp.dot(g_unit, q) * inv_norm * inv_norm * inv_norm)
    return g_q


@wp.func
def conic_adjoint(t0: wp.vec3, t1: wp.vec3, low_pass: float, a: float, b: float, c: float, g: wp.vec3) -> wp.vec3:
    """Gradient with respect to (a, b, c) of covariance_inverse(t0, t1, low_pass, a, b, c) (gaussian_math.py) given
    its output's g, along the guarded chain Warp's generated adjoint runs; the determinant is the forward's
    (covariance_det_scaled), differentiated as an cn - bn^2, which it equals. For a long, thin footprint the chain
    still subtracts nearly equal terms: finite, but float32-conditioned (docs/performance.md, numerical stability)."""
    m = wp.max(a, c)
    s = wp.max(m, 1.0e-12)
    an = a / s
    bn = b / s
    cn = c / s
    dn = covariance_det_scaled(t0, t1, low_pass, s)
    det = wp.max(dn, 1.0e-30)
    k = 1.0 / (det * s)
    g_cn = g[0] * k
    g_bn = -g[1] * k
    g_an = g[2] * k
    g_k = g[0] * cn - g[1] * bn + g[2] * an
    g_denom = -g_k * k * k
    g_det = g_denom * s
    g_s = g_denom * det
    if dn > 1.0e-30:  # the determinant's own derivative, as d(an cn - bn^2), which it equals
        g_an += g_det * cn
        g_cn += g_det * an
        g_bn += -2.0 * bn * g_det
    g_a = g_an / s
    g_b = g_bn / s
    g_c = g_cn / s
    g_s += -(g_an * a + g_bn * b + g_cn * c) / (s * s)
    if m > 1.0e-12:
        if a > c:
            g_a += g_s
        else:
            g_c += g_s
    return wp.vec3(g_a, g_b, g_c)


@wp.func
def sh_adjoint(coeffs: wp.array2d(dtype=wp.vec3), adj_coeffs: wp.array2d(dtype=wp.vec3), write: bool, i: int,
               degree: int, d: wp.vec3, g: wp.vec3) -> wp.vec3:
    """Writes each SH coefficient's gradient (basis value times g, when `write`) and returns the gradient of the
    direction d (what eval_sh's value, dotted with g, changes by as d moves)."""
    x = d[0]
    y = d[1]
    z = d[2]
    if write:
        adj_coeffs[i, 0] = g * SH_C0
    gd = wp.vec3(0.0, 0.0, 0.0)
    if degree > 0:
        w1 = wp.dot(coeffs[i, 1], g)
        w2 = wp.dot(coeffs[i, 2], g)
        w3 = wp.dot(coeffs[i, 3], g)
        gd = gd + wp.vec3(-SH_C1 * w3, -SH_C1 * w1, SH_C1 * w2)
        if write:
            adj_coeffs[i, 1] = g * (-SH_C1 * y)
            adj_coeffs[i, 2] = g * (SH_C1 * z)
            adj_coeffs[i, 3] = g * (-SH_C1 * x)
        if degree > 1:
            xx = x * x
            yy = y * y
            zz = z * z
            w4 = wp.dot(coeffs[i, 4], g)
            w5 = wp.dot(coeffs[i, 5], g)
            w6 = wp.dot(coeffs[i, 6], g)
            w7 = wp.dot(coeffs[i, 7], g)
            w8 = wp.dot(coeffs[i, 8], g)
            gd = gd + wp.vec3(
                SH_C2_0 * y * w4 - 2.0 * SH_C2_2 * x * w6 + SH_C2_3 * z * w7 + 2.0 * SH_C2_4 * x * w8,
                SH_C2_0 * x * w4 + SH_C2_1 * z * w5 - 2.0 * SH_C2_2 * y * w6 - 2.0 * SH_C2_4 * y * w8,
                SH_C2_1 * y * w5 + 4.0 * SH_C2_2 * z * w6 + SH_C2_3 * x * w7)
            if write:
                adj_coeffs[i, 4] = g * (SH_C2_0 * (x * y))
                adj_coeffs[i, 5] = g * (SH_C2_1 * (y * z))
                adj_coeffs[i, 6] = g * (SH_C2_2 * (2.0 * zz - xx - yy))
                adj_coeffs[i, 7] = g * (SH_C2_3 * (x * z))
                adj_coeffs[i, 8] = g * (SH_C2_4 * (xx - yy))
            if degree > 2:
                w9 = wp.dot(coeffs[i, 9], g)
                w10 = wp.dot(coeffs[i, 10], g)
                w11 = wp.dot(coeffs[i, 11], g)
                w12 = wp.dot(coeffs[i, 12], g)
                w13 = wp.dot(coeffs[i, 13], g)
                w14 = wp.dot(coeffs[i, 14], g)
                w15 = wp.dot(coeffs[i, 15], g)
                gd = gd + wp.vec3(
                    SH_C3_0 * 6.0 * x * y * w9 + SH_C3_1 * y * z * w10 - SH_C3_2 * 2.0 * x * y * w11
                    - SH_C3_3 * 6.0 * x * z * w12 + SH_C3_4 * (4.0 * zz - 3.0 * xx - yy) * w13
                    + SH_C3_5 * 2.0 * x * z * w14 + SH_C3_6 * 3.0 * (xx - yy) * w15,
                    SH_C3_0 * 3.0 * (xx - yy) * w9 + SH_C3_1 * x * z * w10 + SH_C3_2 * (4.0 * zz - xx - 3.0 * yy) * w11
                    - SH_C3_3 * 6.0 * y * z * w12 - SH_C3_4 * 2.0 * x * y * w13 - SH_C3_5 * 2.0 * y * z * w14
                    - SH_C3_6 * 6.0 * x * y * w15,
                    SH_C3_1 * x * y * w10 + SH_C3_2 * 8.0 * y * z * w11
                    + SH_C3_3 * (6.0 * zz - 3.0 * xx - 3.0 * yy) * w12 + SH_C3_4 * 8.0 * x * z * w13
                    + SH_C3_5 * (xx - yy) * w14)
                if write:
                    adj_coeffs[i, 9] = g * (SH_C3_0 * y * (3.0 * xx - yy))
                    adj_coeffs[i, 10] = g * (SH_C3_1 * (x * y * z))
                    adj_coeffs[i, 11] = g * (SH_C3_2 * y * (4.0 * zz - xx - yy))
                    adj_coeffs[i, 12] = g * (SH_C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy))
                    adj_coeffs[i, 13] = g * (SH_C3_4 * x * (4.0 * zz - xx - yy))
                    adj_coeffs[i, 14] = g * (SH_C3_5 * z * (xx - yy))
                    adj_coeffs[i, 15] = g * (SH_C3_6 * x * (xx - 3.0 * yy))
    return gd


@wp.kernel
def project_gaussians_adjoint(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    coeffs: wp.array2d(dtype=wp.vec3),  # [N, K]: K=1 plain colours, K>=(d+1)^2 SH
    viewmat: wp.array(dtype=wp.mat44),  # [1]: one camera, not differentiated
    intrinsics: wp.array(dtype=wp.vec4),  # [1] (fx, fy, cx, cy)
    width: int,
    height: int,
    near: float,
    color_mode: int,
    sh_degree: int,
    low_pass: float,
    g_means2d: wp.array(dtype=wp.vec2),  # upstream gradients of the projection's outputs
    g_conics: wp.array(dtype=wp.vec3),
    g_colors: wp.array(dtype=wp.vec3),
    g_depths: wp.array(dtype=float),
    want: int,  # WANT_* bits: which of the gradient arrays below are real
    adj_means: wp.array(dtype=wp.vec3),  # written for each Gaussian with an upstream gradient (zeros elsewhere: the
    # caller's, which hands them zero-filled; a write, not an add, saves reading them back)
    adj_quats: wp.array(dtype=wp.vec4),
    adj_scales: wp.array(dtype=wp.vec3),
    adj_coeffs: wp.array2d(dtype=wp.vec3),
):
    i = wp.tid()
    gm = g_means2d[i]
    gk = g_conics[i]
    gc = g_colors[i]
    gz = g_depths[i]
    # A Gaussian no pixel sent a gradient to has a zero adjoint (NaN counts as a gradient, so it propagates).
    if gm[0] == 0.0 and gm[1] == 0.0 and gk[0] == 0.0 and gk[1] == 0.0 and gk[2] == 0.0 and gc[0] == 0.0 \
            and gc[1] == 0.0 and gc[2] == 0.0 and gz == 0.0:
        return
    V = viewmat[0]
    R = rotation_of(V)
    t = translation_of(V)
    intr = intrinsics[0]
    fx = intr[0]
    fy = intr[1]

    # The forward, as far as the chain rule needs it.
    mu = means[i]
    p = R * mu + t
    z = p[2]
    zs = wp.max(z, near)
    bounds = view_bounds(width, height, intr)
    lo_x = bounds[0]
    hi_x = bounds[1]
    lo_y = bounds[2]
    hi_y = bounds[3]
    xr = p[0] / zs
    yr = p[1] / zs
    xz = wp.clamp(xr, lo_x, hi_x)
    yz = wp.clamp(yr, lo_y, hi_y)
    J = wp.mat33(fx / zs, 0.0, -fx * xz / zs, 0.0, fy / zs, -fy * yz / zs, 0.0, 0.0, 0.0)
    s = scales[i]
    q = quats[i]
    Rq = quat_wxyz_to_rotation(q)
    sx = wp.clamp(s[0], -MAX_SCALE, MAX_SCALE)
    sy = wp.clamp(s[1], -MAX_SCALE, MAX_SCALE)
    sz = wp.clamp(s[2], -MAX_SCALE, MAX_SCALE)
    M = Rq * wp.diag(wp.vec3(sx, sy, sz))
    W = R * M
    T = J * W
    t0 = wp.vec3(T[0, 0], T[0, 1], T[0, 2])
    t1 = wp.vec3(T[1, 0], T[1, 1], T[1, 2])
    a = wp.dot(t0, t0) + low_pass
    b = wp.dot(t0, t1)
    c = wp.dot(t1, t1) + low_pass

    # Backwards: conic -> 2D covariance -> T = J W -> (J, W) -> (camera point, rotation, scales).
    g_abc = conic_adjoint(t0, t1, low_pass, a, b, c, gk)
    g_t0 = t0 * (2.0 * g_abc[0]) + t1 * g_abc[1]
    g_t1 = t0 * g_abc[1] + t1 * (2.0 * g_abc[2])
    g_T = wp.mat33(g_t0[0], g_t0[1], g_t0[2], g_t1[0], g_t1[1], g_t1[2], 0.0, 0.0, 0.0)
    g_J = g_T * wp.transpose(W)
    g_M = wp.transpose(R) * (wp.transpose(J) * g_T)
    inv = 1.0 / zs
    g_zs = gz
    # J = (fx/zs, -fx xz/zs; fy/zs, -fy yz/zs)
    g_zs += -(fx * g_J[0, 0] + fy * g_J[1, 1] - fx * xz * g_J[0, 2] - fy * yz * g_J[1, 2]) * inv * inv
    g_xz = -fx * inv * g_J[0, 2]
    g_yz = -fy * inv * g_J[1, 2]
    g_xr = g_xz * passes_clamp(xr, lo_x, hi_x)
    g_yr = g_yz * passes_clamp(yr, lo_y, hi_y)
    # means2d = (fx p.x / zs + cx, fy p.y / zs + cy); xr = p.x / zs, yr = p.y / zs
    g_px = (gm[0] * fx + g_xr) * inv
    g_py = (gm[1] * fy + g_yr) * inv
    g_zs += -((gm[0] * fx + g_xr) * p[0] + (gm[1] * fy + g_yr) * p[1]) * inv * inv
    g_z = wp.where(z > near, g_zs, 0.0)
    g_mu = wp.transpose(R) * wp.vec3(g_px, g_py, g_z)

    if color_mode == COLOR_SH:
        campos = -(wp.transpose(R) * t)
        dd = mu - campos
        dn2 = wp.dot(dd, dd)
        inv_len = 1.0 / wp.sqrt(wp.max(dn2, 1.0e-24))
        d = dd * inv_len
        rgb_plus = eval_sh(coeffs, i, sh_degree, d) + wp.vec3(0.5, 0.5, 0.5)  # colour_from_sh's clamp side
        g_rgb = wp.vec3(wp.where(rgb_plus[0] >= 0.0, gc[0], 0.0), wp.where(rgb_plus[1] >= 0.0, gc[1], 0.0),
                        wp.where(rgb_plus[2] >= 0.0, gc[2], 0.0))
        g_d = sh_adjoint(coeffs, adj_coeffs, (want & WANT_COEFFS) != 0, i, sh_degree, d, g_rgb)
        g_dd = g_d * inv_len
        if dn2 > 1.0e-24:
            g_dd = g_dd - dd * (wp.dot(g_d, dd) * inv_len * inv_len * inv_len)
        g_mu = g_mu + g_dd
    elif (want & WANT_COEFFS) != 0:
        adj_coeffs[i, 0] = gc

    # A gradient beyond float32 (the chain above overflowing to inf, and inf * 0 making NaN; found on a 1e7-long
    # flat Gaussian at the near plane, before its conic was exact) is dropped (0) when the upstream is finite, never
    # NaN; a NaN upstream still propagates (the guard's signal).
    upstream_finite = wp.isfinite(gm) and wp.isfinite(gk) and wp.isfinite(gc) and wp.isfinite(gz)
    if upstream_finite:
        g_mu = finite_or_zero3(g_mu)
    if (want & WANT_MEANS) != 0:
        adj_means[i] = g_mu
    if (want & WANT_SCALES) != 0:
        # M = Rq diag(scales): each scale's gradient is its column of g_M dotted with Rq's
        g_s = wp.vec3(
            (g_M[0, 0] * Rq[0, 0] + g_M[1, 0] * Rq[1, 0] + g_M[2, 0] * Rq[2, 0]) * passes_clamp(s[0], -MAX_SCALE,
                                                                                               MAX_SCALE),
            (g_M[0, 1] * Rq[0, 1] + g_M[1, 1] * Rq[1, 1] + g_M[2, 1] * Rq[2, 1]) * passes_clamp(s[1], -MAX_SCALE,
                                                                                               MAX_SCALE),
            (g_M[0, 2] * Rq[0, 2] + g_M[1, 2] * Rq[1, 2] + g_M[2, 2] * Rq[2, 2]) * passes_clamp(s[2], -MAX_SCALE,
                                                                                               MAX_SCALE))
        if upstream_finite:
            g_s = finite_or_zero3(g_s)
        adj_scales[i] = g_s
    if (want & WANT_QUATS) != 0:
        g_Rq = g_M * wp.diag(wp.vec3(sx, sy, sz))
        g_q = quat_rotation_adjoint(q, g_Rq)
        if upstream_finite:
            g_q = finite_or_zero4(g_q)
        adj_quats[i] = g_q

