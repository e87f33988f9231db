"""Per-pixel front-to-back alpha blending over a tile's depth-sorted Gaussians, and its hand-written adjoint.

One thread per pixel; a launch covers num_tiles * tile_size² threads so that the threads of one block
share one tile's list. The kernels here are the per-thread versions the CPU runs; `blend_gpu.py` has the
block-cooperative versions of the same per-pixel steps (the @wp.func's below) for GPUs.
Rules as in 3DGS: alpha = min(alpha_max, o exp(-q/2)) with alpha_max = 0.99 (gsplat: 0.999), skip alpha <
alpha_min (1/255), stop before transmittance would drop under t_min (1e-4); all three are per-launch settings
(`BlendParams`): the two thresholds can be traded for speed, the clamp matched to another renderer. The
background is not blended here: the op adds T_final * bg.

The backward walks each pixel's list back to front from the stored stopping point, recovering T_i from
T_final by division (alpha <= alpha_max < 1 keeps that safe). Every output channel (rgb, alpha, depth, inverse
depth, features) is a weighted sum Σ c_i α_i T_i, so the upstream gradients are folded into one scalar
c̃_i = Σ_channels c_i·g per Gaussian and one scalar suffix carries dL/dα_i = T_i (c̃_i − suffix).
"""
import warp as wp


@wp.struct
class BlendParams:
    """What one blend launch needs besides the arrays: image and tile layout, the outputs asked for, and the
    blending thresholds. The CPU and GPU kernels (and their adjoints) all take it, so they cannot drift."""
    width: int
    height: int
    tiles_x: int
    tile_size: int
    first_tile: int  # launches may cover a sub-range of tiles (the CPU splits them over threads)
    want_color: int
    want_depth: int
    want_inv_depth: int
    num_features: int
    alpha_min: float  # contributions below this alpha are skipped
    alpha_max: float  # alpha is clamped here (3DGS: 0.99, gsplat: 0.999); the clamp passes no gradient
    t_min: float  # blending stops before transmittance would drop under this
    depth_eps: float  # > 0: write_pixel also writes the expected depth, Σ w z / max(alpha, depth_eps)
    want_absgrad: int  # 3D adjoints: 1 also sums each pixel's |d means2d| per Gaussian (AbsGS densification)


@wp.func
def pixel_of(tid: int, tiles_x: int, tile_size: int) -> wp.vec2i:
    per_tile = tile_size * tile_size
    tile = tid / per_tile
    local = tid - tile * per_tile
    return wp.vec2i((tile % tiles_x) * tile_size + local % tile_size, (tile / tiles_x) * tile_size + local / tile_size)


@wp.func
def mahalanobis(conic: wp.vec3, dx: float, dy: float) -> float:
    return conic[0] * dx * dx + 2.0 * conic[1] * dx * dy + conic[2] * dy * dy


@wp.struct
class PixelState:
    T: float  # transmittance so far
    rgb: wp.vec3
    depth: float  # Σ w z
    inv_depth: float  # Σ w / z
    last: int  # one past the last blended index of the tile list
    done: int  # 1 once transmittance would drop under t_min
    w: float  # blend weight alpha*T of the last Gaussian blended (the kernels add its features)


@wp.func
def new_pixel_state(start: int) -> PixelState:
    st = PixelState()
    st.T = 1.0
    st.last = start
    return st


@wp.func
def blend_one(st: PixelState, k: int, mean: wp.vec2, conic: wp.vec3, opacity: float, q_cut: float,
              color: wp.vec3, depth: float, fx: float, fy: float, p: BlendParams) -> PixelState:
    """Front-to-back step: blends entry k of the tile list into a pixel's fixed channels. When it was blended
    (st.last == k + 1), the caller adds st.w times its features (scalar loop on the CPU, vectors on GPUs)."""
    dx = fx - mean[0]
    dy = fy - mean[1]
    q = mahalanobis(conic, dx, dy)
    if q > q_cut:  # outside the footprint: alpha would be < alpha_min, skip the exp()
        return st
    alpha = wp.min(p.alpha_max, opacity * wp.exp(-0.5 * q))
    if alpha < p.alpha_min:
        return st
    next_T = st.T * (1.0 - alpha)
    if next_T < p.t_min:
        st.done = 1
        return st
    w = alpha * st.T
    if p.want_color != 0:
        st.rgb = st.rgb + w * color
    if p.want_depth != 0:
        st.depth = st.depth + w * depth
    if p.want_inv_depth != 0:
        st.inv_depth = st.inv_depth + w / depth
    st.w = w
    st.T = next_T
    st.last = k + 1
    return st


@wp.func
def write_pixel(st: PixelState, pix: int, p: BlendParams, out_color: wp.array(dtype=wp.vec3), out_transmittance: wp.array(dtype=float),
                out_alpha: wp.array(dtype=float), out_depth: wp.array(dtype=float),
                out_expected_depth: wp.array(dtype=float), out_inv_depth: wp.array(dtype=float),
                out_last: wp.array(dtype=wp.int32)):
    """out_depth gets the accumulation Σ w z (the adjoint reads it); with p.depth_eps > 0, out_expected_depth gets
    it over max(alpha, depth_eps), torch's division operation for operation (so the same bits), instead of a kernel
    after the blend; the adjoints take it back per pixel (load_pixel_grads)."""
    alpha = 1.0 - st.T
    out_transmittance[pix] = st.T
    out_alpha[pix] = alpha
    out_last[pix] = st.last
    if p.want_color != 0:
        out_color[pix] = st.rgb
    if p.want_depth != 0:
        out_depth[pix] = st.depth
        if p.depth_eps > 0.0:
            out_expected_depth[pix] = st.depth / wp.max(alpha, p.depth_eps)
    if p.want_inv_depth != 0:
        out_inv_depth[pix] = st.inv_depth


@wp.func
def tile_pixel(tid: int, p: BlendParams) -> wp.vec2i:
    """The pixel of launch thread tid (threads of a launch start at tile p.first_tile)."""
    return pixel_of(tid + p.first_tile * p.tile_size * p.tile_size, p.tiles_x, p.tile_size)


@wp.func
def tile_of(tid: int, p: BlendParams) -> int:
    return p.first_tile + tid / (p.tile_size * p.tile_size)


@wp.func
def thread_pixel(tid: int, p: BlendParams):
    """Where blend thread tid works: (inside, pix, tile, fx, fy). inside is False for a thread past the image's
    right or bottom edge (a partial tile; its pix is 0): the per-thread kernels return, the cooperative ones keep it
    to help fetch and sum. pix is the row-major pixel index, tile the tile's index, (fx, fy) the pixel centre."""
    pxy = tile_pixel(tid, p)
    inside = pxy[0] < p.width and pxy[1] < p.height
    pix = wp.where(inside, pxy[1] * p.width + pxy[0], 0)
    return inside, pix, tile_of(tid, p), float(pxy[0]) + 0.5, float(pxy[1]) + 0.5


@wp.struct
class PixelGrads:
    """The upstream gradients at one pixel (zero for outputs not rendered)."""
    rgb: wp.vec3
    alpha: float
    depth: float
    inv_depth: float


@wp.func
def expected_depth_upstream(g: float, grad_alpha: float, T: float, zacc: float, eps: float) -> wp.vec2:
    """(depth accumulation's upstream, alpha's upstream) from the expected depth's upstream g, where the forward
    wrote depth = zacc / max(alpha, eps) and alpha = 1 - T: the division's adjoint as torch computes it, operation
    for operation (div; clamp_min passes a gradient only where alpha >= eps), so the same bits."""
    a = 1.0 - T
    c = wp.max(a, eps)
    share = float(0.0)
    if a >= eps:
        share = -g * ((zacc / c) / c)
    return wp.vec2(g / c, grad_alpha + share)


@wp.func
def load_pixel_grads(pix: int, p: BlendParams, grad_color: wp.array(dtype=wp.vec3), grad_alpha: wp.array(dtype=float),
                     grad_depth: wp.array(dtype=float), grad_inv_depth: wp.array(dtype=float),
                     transmittance: wp.array(dtype=float), zacc: wp.array(dtype=float)) -> PixelGrads:
    """A pixel's upstream gradients. With p.depth_eps > 0 grad_depth is the expected depth's (the forward wrote the
    division), turned here into the accumulation's, its share added to alpha's."""
    up = PixelGrads()
    up.alpha = grad_alpha[pix]
    if p.want_color != 0:
        up.rgb = grad_color[pix]
    if p.want_depth != 0:
        up.depth = grad_depth[pix]
        if p.depth_eps > 0.0 and up.depth != 0.0:  # a zero upstream adds nothing (and no 0 * inf)
            d = expected_depth_upstream(up.depth, up.alpha, transmittance[pix], zacc[pix], p.depth_eps)
            up.depth = d[0]
            up.alpha = d[1]
    if p.want_inv_depth != 0:
        up.inv_depth = grad_inv_depth[pix]
    return up


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
    q_cut: wp.array(dtype=float),
    p: BlendParams,
    out_color: wp.array(dtype=wp.vec3),
    out_transmittance: wp.array(dtype=float),
    out_alpha: wp.array(dtype=float),
    out_depth: wp.array(dtype=float),
    out_expected_depth: wp.array(dtype=float),
    out_inv_depth: wp.array(dtype=float),
    out_features: wp.array2d(dtype=float),
    out_last: wp.array(dtype=wp.int32),
):
    inside, pix, tile, fx, fy = thread_pixel(wp.tid(), p)
    if not inside:
        return
    start = tile_start[tile]
    end = tile_end[tile]

    st = new_pixel_state(start)
    for k in range(start, end):
        g = sorted_ids[k]
        st = blend_one(st, k, means2d[g], conics[g], opacities[g], q_cut[g], colors[g], depths[g], fx, fy, p)
        if st.done != 0:
            break
        if st.last == k + 1:
            for c in range(p.num_features):
                out_features[pix, c] = out_features[pix, c] + st.w * features[g, c]
    write_pixel(st, pix, p, out_color, out_transmittance, out_alpha, out_depth, out_expected_depth, out_inv_depth,
                out_last)


# One pixel's gradient for one Gaussian: d means2d (2), d conic (3), d opacity, d colour (3), d depth,
# 1 if the pixel blended this Gaussian (else all 0), then the pixel's updated T and suffix, and the blend
# weight alpha*T (for feature gradients).
GradRow = wp.types.vector(length=14, dtype=float)
ROW_USED = wp.constant(10)
ROW_T = wp.constant(11)
ROW_SUFFIX = wp.constant(12)
ROW_WEIGHT = wp.constant(13)


@wp.func
def seen_alpha(mean: wp.vec2, conic: wp.vec3, opacity: float, q_cut: float, fx: float, fy: float,
               p: BlendParams) -> wp.vec3:
    """(alpha, o G, G) of a Gaussian at a pixel, alpha = 0 when the blending skips it (outside the footprint or
    alpha < alpha_min). The adjoint's loops test it first, so `pixel_gradient` only runs for blended ones."""
    dx = fx - mean[0]
    dy = fy - mean[1]
    q = mahalanobis(conic, dx, dy)
    if q > q_cut:
        return wp.vec3(0.0)
    G = wp.exp(-0.5 * q)
    raw = opacity * G
    alpha = wp.min(p.alpha_max, raw)
    if alpha < p.alpha_min:
        return wp.vec3(0.0)
    return wp.vec3(alpha, raw, G)


@wp.func
def pixel_gradient(
    mean: wp.vec2, conic: wp.vec3, seen: wp.vec3, color: wp.vec3, depth: float, fx: float, fy: float, T: float,
    suffix: float, up: PixelGrads, feature_dot: float, p: BlendParams,
) -> GradRow:
    """One back-to-front step of the blending adjoint at one pixel, for a Gaussian the pixel blended
    (seen = seen_alpha(...), seen[0] > 0). T is the transmittance behind it; suffix is Σ_channels g·(what is
    seen behind it), per unit transmittance; feature_dot is Σ_c features[g, c]·grad_features[pix, c]."""
    row = GradRow()
    dx = fx - mean[0]
    dy = fy - mean[1]
    cn = conic
    alpha = seen[0]
    raw = seen[1]
    G = seen[2]
    T = T / (1.0 - alpha)  # transmittance in front of this Gaussian
    w = alpha * T
    z = depth
    c_tilde = up.alpha
    if p.want_color != 0:
        c_tilde += wp.dot(color, up.rgb)
        row[6] = w * up.rgb[0]
        row[7] = w * up.rgb[1]
        row[8] = w * up.rgb[2]
    if p.want_depth != 0:
        c_tilde += z * up.depth
    if p.want_inv_depth != 0:
        c_tilde += up.inv_depth / z
    row[9] = w * (up.depth - up.inv_depth / (z * z))
    c_tilde += feature_dot
    d_alpha = T * (c_tilde - suffix)
    if raw < p.alpha_max:  # the clamp has zero derivative
        row[5] = d_alpha * G
        d_q = -0.5 * alpha * d_alpha
        row[2] = d_q * dx * dx
        row[3] = d_q * 2.0 * dx * dy
        row[4] = d_q * dy * dy
        # q depends on the mean through (dx, dy) = pixel - mean
        row[0] = -d_q * 2.0 * (cn[0] * dx + cn[1] * dy)
        row[1] = -d_q * 2.0 * (cn[1] * dx + cn[2] * dy)
    row[ROW_USED] = 1.0
    row[ROW_WEIGHT] = w
    row[ROW_T] = T
    row[ROW_SUFFIX] = alpha * c_tilde + (1.0 - alpha) * suffix
    return row


@wp.func
def add_gradient_row(g: int, row: GradRow, adj_means2d: wp.array(dtype=wp.vec2), adj_conics: wp.array(dtype=wp.vec3),
                     adj_opacities: wp.array(dtype=float), adj_colors: wp.array(dtype=wp.vec3),
                     adj_depths: wp.array(dtype=float), adj_means2d_abs: wp.array(dtype=wp.vec2), want_absgrad: int):
    wp.atomic_add(adj_means2d, g, wp.vec2(row[0], row[1]))
    wp.atomic_add(adj_conics, g, wp.vec3(row[2], row[3], row[4]))
    wp.atomic_add(adj_opacities, g, row[5])
    wp.atomic_add(adj_colors, g, wp.vec3(row[6], row[7], row[8]))
    wp.atomic_add(adj_depths, g, row[9])
    if want_absgrad != 0:
        wp.atomic_add(adj_means2d_abs, g, wp.vec2(wp.abs(row[0]), wp.abs(row[1])))


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
    q_cut: wp.array(dtype=float),
    p: BlendParams,
    transmittance: wp.array(dtype=float),
    last_index: wp.array(dtype=wp.int32),
    zacc: wp.array(dtype=float),  # the forward's depth accumulation (read when p.depth_eps > 0)
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
    adj_means2d_abs: wp.array(dtype=wp.vec2),  # written when p.want_absgrad (a placeholder otherwise)
):
    """The blending adjoint, one thread per pixel, adding each pixel's gradient to global memory (CPU)."""
    inside, pix, tile, fx, fy = thread_pixel(wp.tid(), p)
    if not inside:
        return
    start = tile_start[tile]
    up = load_pixel_grads(pix, p, grad_color, grad_alpha, grad_depth, grad_inv_depth, transmittance, zacc)
    T = transmittance[pix]
    suffix = float(0.0)
    k = last_index[pix] - 1
    while k >= start:
        g = sorted_ids[k]
        k -= 1
        mean = means2d[g]
        seen = seen_alpha(mean, conics[g], opacities[g], q_cut[g], fx, fy, p)
        if seen[0] > 0.0:
            feature_dot = float(0.0)
            for c in range(p.num_features):
                feature_dot += features[g, c] * grad_features[pix, c]
            row = pixel_gradient(mean, conics[g], seen, colors[g], depths[g], fx, fy, T, suffix, up, feature_dot, p)
            T = row[ROW_T]
            suffix = row[ROW_SUFFIX]
            add_gradient_row(g, row, adj_means2d, adj_conics, adj_opacities, adj_colors, adj_depths, adj_means2d_abs,
                             p.want_absgrad)
            for c in range(p.num_features):
                wp.atomic_add(adj_features, g, c, row[ROW_WEIGHT] * grad_features[pix, c])


@wp.kernel
def accumulate(src: wp.array(dtype=float), dst: wp.array(dtype=float)):
    """dst += src (merges the gradient buffers of CPU threads)."""
    i = wp.tid()
    dst[i] = dst[i] + src[i]
