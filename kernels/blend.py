"""Per-pixel front-to-back alpha blending over a tile's depth-sorted Gaussians, and its hand-written adjoint.

One thread per pixel; a launch covers num_tiles * tile_size² threads so that the threads of one block
share one tile's list. Rules as in 3DGS: alpha = min(0.99, o exp(-q/2)), skip alpha < 1/255, stop before
transmittance would drop under 1e-4. The background is not blended here: the op adds T_final * bg.

The backward walks each pixel's list back to front from the stored stopping point, recovering T_i from
T_final by division (alpha <= 0.99 keeps that safe). Every output channel (rgb, alpha, depth, inverse
depth, features) is a weighted sum Σ c_i α_i T_i, so the upstream gradients are folded into one scalar
c̃_i = Σ_channels c_i·g per Gaussian and one scalar suffix carries dL/dα_i = T_i (c̃_i − suffix).
"""
import warp as wp

ALPHA_MIN = wp.constant(1.0 / 255.0)
ALPHA_MAX = wp.constant(0.99)
T_MIN = wp.constant(1.0e-4)


@wp.func
def pixel_of(tid: int, tiles_x: int, tile_size: int) -> wp.vec2i:
    per_tile = tile_size * tile_size
    tile = tid / per_tile
    local = tid - tile * per_tile
    return wp.vec2i((tile % tiles_x) * tile_size + local % tile_size, (tile / tiles_x) * tile_size + local / tile_size)


@wp.func
def mahalanobis(conic: wp.vec3, dx: float, dy: float) -> float:
    return conic[0] * dx * dx + 2.0 * conic[1] * dx * dy + conic[2] * dy * dy


@wp.kernel
def blend_forward(
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    colors: wp.array(dtype=wp.vec3),
    depths: wp.array(dtype=float),
    features: wp.array2d(dtype=float),
    width: int,
    height: int,
    tiles_x: int,
    tile_size: int,
    first_tile: int,  # launches may cover a sub-range of tiles (the CPU splits them over threads)
    q_cut: wp.array(dtype=float),
    want_color: int,
    want_depth: int,
    want_inv_depth: int,
    num_features: int,
    out_color: wp.array(dtype=wp.vec3),
    out_transmittance: wp.array(dtype=float),
    out_alpha: wp.array(dtype=float),
    out_depth: wp.array(dtype=float),
    out_inv_depth: wp.array(dtype=float),
    out_features: wp.array2d(dtype=float),
    out_last: wp.array(dtype=wp.int32),
):
    tid = wp.tid() + first_tile * tile_size * tile_size
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
    z_acc = float(0.0)
    inv_acc = float(0.0)
    last = start
    for k in range(start, end):
        g = sorted_ids[k]
        m = means2d[g]
        dx = fx - m[0]
        dy = fy - m[1]
        q = mahalanobis(conics[g], dx, dy)
        if q > q_cut[g]:
            continue
        alpha = wp.min(ALPHA_MAX, opacities[g] * wp.exp(-0.5 * q))
        if alpha < ALPHA_MIN:
            continue
        next_T = T * (1.0 - alpha)
        if next_T < T_MIN:
            break
        w = alpha * T
        if want_color != 0:
            rgb += w * colors[g]
        if want_depth != 0:
            z_acc += w * depths[g]
        if want_inv_depth != 0:
            inv_acc += w / depths[g]
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


@wp.kernel
def blend_backward(
    tile_start: wp.array(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    colors: wp.array(dtype=wp.vec3),
    depths: wp.array(dtype=float),
    features: wp.array2d(dtype=float),
    width: int,
    height: int,
    tiles_x: int,
    tile_size: int,
    first_tile: int,  # launches may cover a sub-range of tiles (the CPU splits them over threads)
    q_cut: wp.array(dtype=float),
    want_color: int,
    want_depth: int,
    want_inv_depth: int,
    num_features: int,
    transmittance: wp.array(dtype=float),
    last_index: wp.array(dtype=wp.int32),
    grad_color: wp.array(dtype=wp.vec3),
    grad_alpha: wp.array(dtype=float),
    grad_depth: wp.array(dtype=float),
    grad_inv_depth: wp.array(dtype=float),
    grad_features: wp.array2d(dtype=float),
    adj_means2d: wp.array(dtype=wp.vec2),
    adj_conics: wp.array(dtype=wp.vec3),
    adj_opacities: wp.array(dtype=float),
    adj_colors: wp.array(dtype=wp.vec3),
    adj_depths: wp.array(dtype=float),
    adj_features: wp.array2d(dtype=float),
):
    tid = wp.tid() + first_tile * tile_size * tile_size
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

    T = transmittance[pix]  # transmittance behind the current Gaussian, walking back to front
    suffix = float(0.0)  # Σ_channels g·(what is seen behind the current Gaussian), per unit transmittance
    k = last_index[pix] - 1
    while k >= start:
        g = sorted_ids[k]
        k -= 1
        m = means2d[g]
        dx = fx - m[0]
        dy = fy - m[1]
        cn = conics[g]
        q = mahalanobis(cn, dx, dy)
        if q > q_cut[g]:
            continue
        o = opacities[g]
        G = wp.exp(-0.5 * q)
        raw = o * G
        alpha = wp.min(ALPHA_MAX, raw)
        if alpha < ALPHA_MIN:
            continue
        T = T / (1.0 - alpha)  # transmittance in front of this Gaussian
        w = alpha * T
        z = depths[g]

        c_tilde = g_alpha
        if want_color != 0:
            c_tilde += wp.dot(colors[g], g_rgb)
            wp.atomic_add(adj_colors, g, w * g_rgb)
        if want_depth != 0:
            c_tilde += z * g_z
        if want_inv_depth != 0:
            c_tilde += g_inv / z
        if want_depth != 0 or want_inv_depth != 0:
            wp.atomic_add(adj_depths, g, w * (g_z - g_inv / (z * z)))
        for c in range(num_features):
            gf = grad_features[pix, c]
            c_tilde += features[g, c] * gf
            wp.atomic_add(adj_features, g, c, w * gf)

        d_alpha = T * (c_tilde - suffix)
        suffix = alpha * c_tilde + (1.0 - alpha) * suffix
        if raw < ALPHA_MAX:  # the 0.99 clamp has zero derivative
            wp.atomic_add(adj_opacities, g, d_alpha * G)
            d_q = -0.5 * alpha * d_alpha
            wp.atomic_add(adj_conics, g, d_q * wp.vec3(dx * dx, 2.0 * dx * dy, dy * dy))
            # q depends on the mean through (dx, dy) = pixel - mean
            wp.atomic_add(
                adj_means2d, g, -d_q * wp.vec2(2.0 * (cn[0] * dx + cn[1] * dy), 2.0 * (cn[1] * dx + cn[2] * dy))
            )


@wp.kernel
def accumulate(src: wp.array(dtype=float), dst: wp.array(dtype=float)):
    """dst += src (merges the gradient buffers of CPU threads)."""
    i = wp.tid()
    dst[i] = dst[i] + src[i]
