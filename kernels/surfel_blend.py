"""Per-pixel front-to-back blending of depth-sorted surfels, and its hand-written back-to-front adjoint.

Per pixel and surfel: intersect the planes x = px and y = py (through the pixel's ray) in surfel coordinates,
h_u = px M_z - M_x, h_v = py M_z - M_y, (u, v) from h_u x h_v; s3 = u^2 + v^2 at the hit (a miss, or a hit
closer than `near`, counts as s3 = inf). The screen-space fallback s2 = 2 |pixel - centre|^2 keeps splats seen
edge-on visible: G = exp(-min(s3, s2)/2), and the depth is the hit's camera z when s3 wins, the centre's
otherwise. Then the 3DGS rules: alpha = min(0.99, o G), skip alpha < 1/255, stop before T < 1e-4.

Outputs are weighted sums Σ w_i c_i (w_i = alpha_i T_i) plus two that are not:
- median depth: z of the last surfel blended while T > 0.5 (where accumulated opacity crosses 0.5);
- distortion (2DGS): Σ_{i<j} w_i w_j (m_i - m_j)^2 with m = -k / z (2DGS's NDC depth up to a constant,
  which cancels). It equals W S2 - S1^2 with W = Σ w, S1 = Σ w m, S2 = Σ w m^2, so it is linear in w at
  fixed totals and its gradient folds into the same scalar suffix as the other channels. m is taken
  relative to the pixel's first blended surfel to avoid cancellation in float32 (the term is shift-invariant).

The adjoint walks back to front from the stopping point, recovering T_i from T_final by division.
"""
import warp as wp

from .blend import ALPHA_MAX, ALPHA_MIN, T_MIN, pixel_of
from .surfel_project import FILTER_INV_SQUARE

MISS = wp.constant(3.0e38)
MAX_S3 = wp.constant(1.0e30)


@wp.func
def ray_splat(M: wp.mat33, px: float, py: float, near: float) -> wp.vec4:
    """(s3, z, u, v) where the pixel's ray meets the surfel plane; s3 = MISS when it does not (in front)."""
    zeta = wp.cross(px * M[2] - M[0], py * M[2] - M[1])
    s3 = MISS
    z = float(0.0)
    u = float(0.0)
    v = float(0.0)
    if zeta[2] != 0.0:
        u = zeta[0] / zeta[2]
        v = zeta[1] / zeta[2]
        s = u * u + v * v
        zi = u * M[2, 0] + v * M[2, 1] + M[2, 2]
        if s < MAX_S3 and zi >= near:
            s3 = s
            z = zi
    return wp.vec4(s3, z, u, v)


@wp.func
def screen_weight(m: wp.vec2, px: float, py: float) -> float:
    dx = px - m[0]
    dy = py - m[1]
    return FILTER_INV_SQUARE * (dx * dx + dy * dy)


@wp.kernel
def blend_forward(
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    transforms: wp.array(dtype=wp.mat33),
    means2d: wp.array(dtype=wp.vec2),
    depths: wp.array(dtype=float),
    opacities: wp.array(dtype=float),
    colors: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    features: wp.array2d(dtype=float),
    width: int,
    height: int,
    tiles_x: int,
    tile_size: int,
    q_cut: wp.array(dtype=float),
    near: float,
    dist_scale: float,
    want_color: int,
    want_depth: int,
    want_inv_depth: int,
    want_normal: int,
    want_median: int,
    want_distortion: int,
    num_features: int,
    out_color: wp.array(dtype=wp.vec3),
    out_transmittance: wp.array(dtype=float),
    out_alpha: wp.array(dtype=float),
    out_depth: wp.array(dtype=float),
    out_inv_depth: wp.array(dtype=float),
    out_normal: wp.array(dtype=wp.vec3),
    out_median: wp.array(dtype=float),
    out_median_index: wp.array(dtype=wp.int32),
    out_distortion: wp.array(dtype=float),
    out_dist_stats: wp.array(dtype=wp.vec3),  # (m_ref, S1, S2) for the adjoint
    out_features: wp.array2d(dtype=float),
    out_last: wp.array(dtype=wp.int32),
):
    tid = wp.tid()
    pxy = pixel_of(tid, tiles_x, tile_size)
    if pxy[0] >= width or pxy[1] >= height:
        return
    pix = pxy[1] * width + pxy[0]
    tile = tid / (tile_size * tile_size)
    start = tile_start[tile]
    end = tile_end[tile]
    fx = float(pxy[0]) + 0.5
    fy = float(pxy[1]) + 0.5

    T = float(1.0)
    rgb = wp.vec3(0.0)
    nrm = wp.vec3(0.0)
    z_acc = float(0.0)
    inv_acc = float(0.0)
    median = float(0.0)
    median_k = int(-1)
    m_ref = float(0.0)
    s1 = float(0.0)
    s2 = float(0.0)
    first = int(1)
    last = start
    for k in range(start, end):
        g = sorted_ids[k]
        hit = ray_splat(transforms[g], fx, fy, near)
        s_screen = screen_weight(means2d[g], fx, fy)
        s = s_screen
        z = depths[g]
        if hit[0] <= s_screen:
            s = hit[0]
            z = hit[1]
        if s > q_cut[g]:
            continue
        alpha = wp.min(ALPHA_MAX, opacities[g] * wp.exp(-0.5 * s))
        if alpha < ALPHA_MIN:
            continue
        next_T = T * (1.0 - alpha)
        if next_T < T_MIN:
            break
        w = alpha * T
        if want_color != 0:
            rgb += w * colors[g]
        if want_depth != 0:
            z_acc += w * z
        if want_inv_depth != 0:
            inv_acc += w / z
        if want_normal != 0:
            nrm += w * normals[g]
        if want_median != 0 and T > 0.5:
            median = z
            median_k = k
        if want_distortion != 0:
            m = -dist_scale / z
            if first != 0:
                m_ref = m
                first = 0
            dm = m - m_ref
            s1 += w * dm
            s2 += w * dm * dm
        for c in range(num_features):
            out_features[pix, c] = out_features[pix, c] + w * features[g, c]
        T = next_T
        last = k + 1

    out_transmittance[pix] = T
    out_alpha[pix] = 1.0 - T
    out_last[pix] = last
    if want_color != 0:
        out_color[pix] = rgb
    if want_depth != 0:
        out_depth[pix] = z_acc
    if want_inv_depth != 0:
        out_inv_depth[pix] = inv_acc
    if want_normal != 0:
        out_normal[pix] = nrm
    if want_median != 0:
        out_median[pix] = median
        out_median_index[pix] = median_k
    if want_distortion != 0:
        out_distortion[pix] = (1.0 - T) * s2 - s1 * s1
        out_dist_stats[pix] = wp.vec3(m_ref, s1, s2)


@wp.kernel
def blend_backward(
    tile_start: wp.array(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    transforms: wp.array(dtype=wp.mat33),
    means2d: wp.array(dtype=wp.vec2),
    depths: wp.array(dtype=float),
    opacities: wp.array(dtype=float),
    colors: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    features: wp.array2d(dtype=float),
    width: int,
    height: int,
    tiles_x: int,
    tile_size: int,
    q_cut: wp.array(dtype=float),
    near: float,
    dist_scale: float,
    want_color: int,
    want_depth: int,
    want_inv_depth: int,
    want_normal: int,
    want_median: int,
    want_distortion: int,
    num_features: int,
    transmittance: wp.array(dtype=float),
    last_index: wp.array(dtype=wp.int32),
    median_index: wp.array(dtype=wp.int32),
    dist_stats: wp.array(dtype=wp.vec3),
    grad_color: wp.array(dtype=wp.vec3),
    grad_alpha: wp.array(dtype=float),
    grad_depth: wp.array(dtype=float),
    grad_inv_depth: wp.array(dtype=float),
    grad_normal: wp.array(dtype=wp.vec3),
    grad_median: wp.array(dtype=float),
    grad_distortion: wp.array(dtype=float),
    grad_features: wp.array2d(dtype=float),
    adj_transforms: wp.array(dtype=wp.mat33),
    adj_means2d: wp.array(dtype=wp.vec2),
    adj_depths: wp.array(dtype=float),
    adj_opacities: wp.array(dtype=float),
    adj_colors: wp.array(dtype=wp.vec3),
    adj_normals: wp.array(dtype=wp.vec3),
    adj_features: wp.array2d(dtype=float),
):
    tid = wp.tid()
    pxy = pixel_of(tid, tiles_x, tile_size)
    if pxy[0] >= width or pxy[1] >= height:
        return
    pix = pxy[1] * width + pxy[0]
    tile = tid / (tile_size * tile_size)
    start = tile_start[tile]
    fx = float(pxy[0]) + 0.5
    fy = float(pxy[1]) + 0.5

    g_alpha = grad_alpha[pix]
    g_rgb = wp.vec3(0.0)
    if want_color != 0:
        g_rgb = grad_color[pix]
    g_z = float(0.0)
    if want_depth != 0:
        g_z = grad_depth[pix]
    g_inv = float(0.0)
    if want_inv_depth != 0:
        g_inv = grad_inv_depth[pix]
    g_n = wp.vec3(0.0)
    if want_normal != 0:
        g_n = grad_normal[pix]
    g_med = float(0.0)
    med_k = int(-1)
    if want_median != 0:
        g_med = grad_median[pix]
        med_k = median_index[pix]
    g_dist = float(0.0)
    m_ref = float(0.0)
    s1 = float(0.0)
    s2 = float(0.0)
    if want_distortion != 0:
        g_dist = grad_distortion[pix]
        st = dist_stats[pix]
        m_ref = st[0]
        s1 = st[1]
        s2 = st[2]

    T_final = transmittance[pix]
    W = 1.0 - T_final
    T = T_final  # transmittance behind the current surfel, walking back to front
    suffix = float(0.0)  # Σ_channels g·(what is seen behind the current surfel), per unit transmittance
    k = last_index[pix] - 1
    while k >= start:
        kk = k
        g = sorted_ids[k]
        k -= 1
        M = transforms[g]
        hit = ray_splat(M, fx, fy, near)
        mean = means2d[g]
        s_screen = screen_weight(mean, fx, fy)
        use_hit = hit[0] <= s_screen
        s = s_screen
        z = depths[g]
        if use_hit:
            s = hit[0]
            z = hit[1]
        if s > q_cut[g]:
            continue
        o = opacities[g]
        G = wp.exp(-0.5 * s)
        raw = o * G
        alpha = wp.min(ALPHA_MAX, raw)
        if alpha < ALPHA_MIN:
            continue
        T = T / (1.0 - alpha)  # transmittance in front of this surfel
        w = alpha * T

        # c_tilde: d(loss)/d(w) of this surfel; d_z: d(loss)/d(z) at fixed weights.
        c_tilde = g_alpha
        d_z = float(0.0)
        if want_color != 0:
            c_tilde += wp.dot(colors[g], g_rgb)
            wp.atomic_add(adj_colors, g, w * g_rgb)
        if want_depth != 0:
            c_tilde += z * g_z
            d_z += w * g_z
        if want_inv_depth != 0:
            c_tilde += g_inv / z
            d_z -= w * g_inv / (z * z)
        if want_normal != 0:
            c_tilde += wp.dot(normals[g], g_n)
            wp.atomic_add(adj_normals, g, w * g_n)
        if want_median != 0 and kk == med_k:
            d_z += g_med
        if want_distortion != 0:
            dm = -dist_scale / z - m_ref
            c_tilde += g_dist * (s2 - 2.0 * s1 * dm + W * dm * dm)
            d_z += g_dist * 2.0 * w * (W * dm - s1) * dist_scale / (z * z)
        for c in range(num_features):
            gf = grad_features[pix, c]
            c_tilde += features[g, c] * gf
            wp.atomic_add(adj_features, g, c, w * gf)

        d_alpha = T * (c_tilde - suffix)
        suffix = alpha * c_tilde + (1.0 - alpha) * suffix
        d_s = float(0.0)
        if raw < ALPHA_MAX:  # the 0.99 clamp has zero derivative
            wp.atomic_add(adj_opacities, g, d_alpha * G)
            d_s = -0.5 * alpha * d_alpha

        if use_hit:
            # s3 = u^2 + v^2 and z = (u, v, 1)·M_z, with (u, v) = (zeta_x, zeta_y) / zeta_z.
            u = hit[2]
            v = hit[3]
            g_u = 2.0 * u * d_s + M[2, 0] * d_z
            g_v = 2.0 * v * d_s + M[2, 1] * d_z
            h_u = fx * M[2] - M[0]
            h_v = fy * M[2] - M[1]
            zeta = wp.cross(h_u, h_v)
            inv = 1.0 / zeta[2]  # nonzero: the hit was used
            d_zeta = wp.vec3(g_u * inv, g_v * inv, -(g_u * u + g_v * v) * inv)
            d_hu = wp.cross(h_v, d_zeta)  # zeta = h_u x h_v
            d_hv = wp.cross(d_zeta, h_u)
            d_row_z = fx * d_hu + fy * d_hv + d_z * wp.vec3(u, v, 1.0)
            wp.atomic_add(adj_transforms, g, wp.mat33(
                -d_hu[0], -d_hu[1], -d_hu[2],
                -d_hv[0], -d_hv[1], -d_hv[2],
                d_row_z[0], d_row_z[1], d_row_z[2],
            ))
        else:
            # s2 = 2 |pixel - mean|^2; the depth is the centre's.
            wp.atomic_add(adj_means2d, g, -2.0 * FILTER_INV_SQUARE * d_s * wp.vec2(fx - mean[0], fy - mean[1]))
            wp.atomic_add(adj_depths, g, d_z)
