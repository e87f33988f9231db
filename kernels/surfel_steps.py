"""The per-pixel @wp.func steps of surfel blending, shared by the per-thread kernels (surfel_blend.py, the CPU)
and the block-cooperative ones (surfel_blend_gpu.py, GPUs).

Per pixel and surfel: intersect the planes x = px and y = py (through the pixel's ray) in surfel coordinates,
h_u = px M_z - M_x, h_v = py M_z - M_y, (u, v) from h_u x h_v; s3 = u^2 + v^2 at the hit (a miss, or a hit
closer than `near`, counts as s3 = inf). The screen-space fallback s2 = |pixel - centre|^2 / sigma^2 (2DGS: sigma
1/sqrt(2) px; the render op's `screen_sigma`) keeps splats seen edge-on visible: G = exp(-min(s3, s2)/2), and the depth is the hit's camera z when s3 wins, the centre's
otherwise. Then the 3DGS rules: alpha = min(0.99, o G), skip alpha < alpha_min (1/255), stop before T < t_min
(1e-4); the thresholds and the other per-launch settings come in one `SurfelBlendParams`.

Outputs are weighted sums Σ w_i c_i (w_i = alpha_i T_i) plus two that are not:
- median depth: z of the last surfel blended while T > 0.5 (where accumulated opacity crosses 0.5);
- distortion (2DGS): Σ_{i<j} w_i w_j (m_i - m_j)^2 with m = -k / z (2DGS's NDC depth up to a constant,
  which cancels). It equals W S2 - S1^2 with W = Σ w, S1 = Σ w m, S2 = Σ w m^2, so it is linear in w at
  fixed totals and its gradient folds into the same scalar suffix as the other channels. m is taken
  relative to the pixel's first blended surfel to avoid cancellation in float32 (the term is shift-invariant).

The adjoint walks back to front from the stopping point, recovering T_i from T_final by division.

The per-pixel maths are @wp.func steps shared by the per-thread kernels here (what the CPU runs) and the
block-cooperative kernels of `surfel_blend_gpu.py` (GPUs): `splat_point` (which Gaussian a pixel sees and at
what depth) and `blend_alpha` for both passes, `SurfelPixelState` / `blend_surfel` / `write_surfel_pixel` for
the forward, `SurfelPixelGrads` / `surfel_pixel_gradient` -> `SurfelGradRow` / `add_surfel_gradient_row` for the
backward. The kernels' loops make the skip / stop decisions (outside the footprint, alpha < alpha_min, saturation)
before calling the steps, which are then straight-line. Steps that made those decisions themselves (returning
the state or a zero row unchanged on a skip, the loop testing a flag afterwards) measured 1.3x (forward) and
1.5-2x (backward) slower on the CPU than the monolithic kernels they replaced; this layout matches the forward
and is within ~10% on the backward.
"""
import warp as wp

from .blend import BlendParams, expected_depth_upstream

# The blend adjoint is hand-written from these steps: Warp's generated adjoints are never used, so skip them.
wp.set_module_options({"enable_backward": False})

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
def screen_weight(m: wp.vec2, px: float, py: float, filter_inv: float) -> float:
    dx = px - m[0]
    dy = py - m[1]
    return filter_inv * (dx * dx + dy * dy)


# What a pixel sees of a surfel: (s, z, u, v, hit) with G = exp(-s/2) and z its depth; hit = 1 when the ray-splat
# intersection won (then (u, v) is where), 0 for the screen-space fallback (depth: the centre's).
SplatPoint = wp.types.vector(length=5, dtype=float)


@wp.func
def splat_point(M: wp.mat33, mean: wp.vec2, center_depth: float, px: float, py: float, near: float,
                filter_inv: float) -> SplatPoint:
    hit = ray_splat(M, px, py, near)
    s_screen = screen_weight(mean, px, py, filter_inv)
    s = s_screen
    z = center_depth
    used = float(0.0)
    if hit[0] <= s_screen:
        s = hit[0]
        z = hit[1]
        used = 1.0
    return SplatPoint(s, z, hit[2], hit[3], used)


@wp.func
def blend_alpha(opacity: float, G: float, alpha_max: float) -> float:
    """alpha from G = exp(-s/2); worth the exp() only when s <= q_cut. Skip the surfel if alpha < alpha_min."""
    return wp.min(alpha_max, opacity * G)


@wp.func
def saturates(T: float, alpha: float, t_min: float) -> bool:
    """Blending stops before a surfel that would take the transmittance under t_min."""
    return T * (1.0 - alpha) < t_min


@wp.struct
class SurfelBlendParams:
    """Per-launch settings of the surfel blend kernels: the 3D kernels' (layout, rgb/depth/inverse-depth/feature
    flags, thresholds) plus the surfel-only ones."""
    base: BlendParams
    near: float  # ray hits closer than this are misses
    filter_inv: float  # 1 / sigma^2 of the screen-space fallback (2DGS: 2, sigma = 1/sqrt(2) px)
    dist_scale: float  # k of the distortion's m = -k / z
    want_normal: int
    want_median: int
    want_distortion: int


# ---- forward ---------------------------------------------------------------------------------------------------

@wp.struct
class SurfelPixelState:
    T: float  # transmittance so far
    rgb: wp.vec3
    normal: wp.vec3
    depth: float  # Σ w z
    inv_depth: float  # Σ w / z
    median: float  # z of the last surfel blended while T > 0.5
    median_k: int  # its index in the tile list (-1: none)
    m_ref: float  # distortion: m of the first blended surfel, which the statistics are relative to
    s1: float  # Σ w (m - m_ref)
    s2: float  # Σ w (m - m_ref)^2
    first: int  # 1 until a surfel has been blended
    last: int  # one past the last blended index of the tile list


@wp.func
def new_surfel_state(start: int) -> SurfelPixelState:
    st = SurfelPixelState()
    st.T = 1.0
    st.median_k = -1
    st.first = 1
    st.last = start
    return st


@wp.func
def blend_surfel(st: SurfelPixelState, k: int, alpha: float, z: float, color: wp.vec3, normal: wp.vec3,
                 p: SurfelBlendParams) -> SurfelPixelState:
    """Front-to-back step: blends entry k of the tile list, seen with `alpha` at depth z, into a pixel's fixed
    channels. The caller has checked that alpha >= alpha_min and that it does not saturate the pixel, and adds
    the features with weight alpha * T (scalar loop on the CPU, vectors on GPUs)."""
    w = alpha * st.T
    if p.base.want_color != 0:
        st.rgb = st.rgb + w * color
    if p.base.want_depth != 0:
        st.depth = st.depth + w * z
    if p.base.want_inv_depth != 0:
        st.inv_depth = st.inv_depth + w / z
    if p.want_normal != 0:
        st.normal = st.normal + w * normal
    if p.want_median != 0 and st.T > 0.5:
        st.median = z
        st.median_k = k
    if p.want_distortion != 0:
        m = -p.dist_scale / z
        if st.first != 0:
            st.m_ref = m
        dm = m - st.m_ref
        st.s1 = st.s1 + w * dm
        st.s2 = st.s2 + w * dm * dm
    st.first = 0
    st.T = st.T * (1.0 - alpha)
    st.last = k + 1
    return st


@wp.func
def write_surfel_pixel(st: SurfelPixelState, pix: int, p: SurfelBlendParams,
                       out_color: wp.array(dtype=wp.vec3), out_transmittance: wp.array(dtype=float),
                       out_alpha: wp.array(dtype=float), out_depth: wp.array(dtype=float),
                       out_expected_depth: wp.array(dtype=float),
                       out_inv_depth: wp.array(dtype=float), out_normal: wp.array(dtype=wp.vec3),
                       out_median: wp.array(dtype=float), out_median_index: wp.array(dtype=wp.int32),
                       out_distortion: wp.array(dtype=float), out_dist_stats: wp.array(dtype=wp.vec3),
                       out_last: wp.array(dtype=wp.int32)):
    """As blend.write_pixel: out_depth gets the accumulation, and with p.base.depth_eps > 0 out_expected_depth
    gets it over alpha."""
    alpha = 1.0 - st.T
    out_transmittance[pix] = st.T
    out_alpha[pix] = alpha
    out_last[pix] = st.last
    if p.base.want_color != 0:
        out_color[pix] = st.rgb
    if p.base.want_depth != 0:
        out_depth[pix] = st.depth
        if p.base.depth_eps > 0.0:
            out_expected_depth[pix] = st.depth / wp.max(alpha, p.base.depth_eps)
    if p.base.want_inv_depth != 0:
        out_inv_depth[pix] = st.inv_depth
    if p.want_normal != 0:
        out_normal[pix] = st.normal
    if p.want_median != 0:
        out_median[pix] = st.median
        out_median_index[pix] = st.median_k
    if p.want_distortion != 0:
        out_distortion[pix] = (1.0 - st.T) * st.s2 - st.s1 * st.s1
        out_dist_stats[pix] = wp.vec3(st.m_ref, st.s1, st.s2)


# ---- backward --------------------------------------------------------------------------------------------------

@wp.struct
class SurfelPixelGrads:
    """A pixel's upstream gradients and the forward statistics its adjoint needs."""
    alpha: float
    rgb: wp.vec3
    depth: float
    inv_depth: float
    normal: wp.vec3
    median: float
    median_k: int  # tile-list index of the median surfel
    distortion: float
    m_ref: float
    s1: float
    s2: float
    W: float  # 1 - T_final: the total blend weight


@wp.func
def load_pixel_grads(pix: int, p: SurfelBlendParams, transmittance: wp.array(dtype=float),
                     median_index: wp.array(dtype=wp.int32), dist_stats: wp.array(dtype=wp.vec3),
                     zacc: wp.array(dtype=float),
                     grad_color: wp.array(dtype=wp.vec3), grad_alpha: wp.array(dtype=float),
                     grad_depth: wp.array(dtype=float), grad_inv_depth: wp.array(dtype=float),
                     grad_normal: wp.array(dtype=wp.vec3), grad_median: wp.array(dtype=float),
                     grad_distortion: wp.array(dtype=float)) -> SurfelPixelGrads:
    pg = SurfelPixelGrads()
    pg.alpha = grad_alpha[pix]
    if p.base.want_color != 0:
        pg.rgb = grad_color[pix]
    if p.base.want_depth != 0:
        pg.depth = grad_depth[pix]
        if p.base.depth_eps > 0.0 and pg.depth != 0.0:  # the expected depth's upstream (blend.load_pixel_grads)
            d = expected_depth_upstream(pg.depth, pg.alpha, transmittance[pix], zacc[pix], p.base.depth_eps)
            pg.depth = d[0]
            pg.alpha = d[1]
    if p.base.want_inv_depth != 0:
        pg.inv_depth = grad_inv_depth[pix]
    if p.want_normal != 0:
        pg.normal = grad_normal[pix]
    pg.median_k = -1
    if p.want_median != 0:
        pg.median = grad_median[pix]
        pg.median_k = median_index[pix]
    if p.want_distortion != 0:
        pg.distortion = grad_distortion[pix]
        st = dist_stats[pix]
        pg.m_ref = st[0]
        pg.s1 = st[1]
        pg.s2 = st[2]
    pg.W = 1.0 - transmittance[pix]
    return pg


# One pixel's gradient for one surfel: d transform (9, row-major), d means2d (2), d centre depth, d opacity,
# d colour (3), d normal (3); whether the ray hit (ROW_HIT) or the screen-space fallback (ROW_SCREEN) was
# blended (both 0: the pixel skipped this surfel, and every entry is 0); then the pixel's updated T and suffix,
# and the blend weight alpha*T (for feature gradients). The hit puts its gradient in the transform only, the
# fallback in means2d and depth only.
SurfelGradRow = wp.types.vector(length=24, dtype=float)
ROW_TRANSFORM = wp.constant(0)
ROW_MEAN = wp.constant(9)
ROW_DEPTH = wp.constant(11)
ROW_OPACITY = wp.constant(12)
ROW_COLOR = wp.constant(13)
ROW_NORMAL = wp.constant(16)
ROW_HIT = wp.constant(19)
ROW_SCREEN = wp.constant(20)
ROW_T = wp.constant(21)
ROW_SUFFIX = wp.constant(22)
ROW_WEIGHT = wp.constant(23)


@wp.func
def surfel_pixel_gradient(
    k: int, sp: SplatPoint, M: wp.mat33, mean: wp.vec2, opacity: float, G: float, color: wp.vec3,
    normal: wp.vec3, fx: float, fy: float, T: float, suffix: float, pg: SurfelPixelGrads,
    feature_dot: float, p: SurfelBlendParams,
) -> SurfelGradRow:
    """One back-to-front step of the blending adjoint at one pixel, for entry k of the tile list, which the
    pixel blended: sp = splat_point(...), G = exp(-s/2), blend_alpha(opacity, G) >= alpha_min.
    T is the transmittance behind this surfel; suffix is Σ_channels g·(what is seen behind it), per unit
    transmittance; feature_dot is Σ_c features[g, c]·grad_features[pix, c]."""
    row = SurfelGradRow()
    z = sp[1]
    raw = opacity * G
    alpha = wp.min(p.base.alpha_max, raw)
    T = T / (1.0 - alpha)  # transmittance in front of this surfel
    w = alpha * T

    # c_tilde: d(loss)/d(w) of this surfel; d_z: d(loss)/d(z) at fixed weights.
    c_tilde = pg.alpha
    d_z = float(0.0)
    if p.base.want_color != 0:
        c_tilde += wp.dot(color, pg.rgb)
        row[ROW_COLOR + 0] = w * pg.rgb[0]
        row[ROW_COLOR + 1] = w * pg.rgb[1]
        row[ROW_COLOR + 2] = w * pg.rgb[2]
    if p.base.want_depth != 0:
        c_tilde += z * pg.depth
        d_z += w * pg.depth
    if p.base.want_inv_depth != 0:
        c_tilde += pg.inv_depth / z
        d_z -= w * pg.inv_depth / (z * z)
    if p.want_normal != 0:
        c_tilde += wp.dot(normal, pg.normal)
        row[ROW_NORMAL + 0] = w * pg.normal[0]
        row[ROW_NORMAL + 1] = w * pg.normal[1]
        row[ROW_NORMAL + 2] = w * pg.normal[2]
    if p.want_median != 0 and k == pg.median_k:
        d_z += pg.median
    if p.want_distortion != 0:
        dm = -p.dist_scale / z - pg.m_ref
        c_tilde += pg.distortion * (pg.s2 - 2.0 * pg.s1 * dm + pg.W * dm * dm)
        d_z += pg.distortion * 2.0 * w * (pg.W * dm - pg.s1) * p.dist_scale / (z * z)
    c_tilde += feature_dot  # Σ_c features[g, c] grad_features[pix, c]

    d_alpha = T * (c_tilde - suffix)
    d_s = float(0.0)
    if raw < p.base.alpha_max:  # the clamp has zero derivative
        row[ROW_OPACITY] = d_alpha * G
        d_s = -0.5 * alpha * d_alpha

    if sp[4] != 0.0:
        # s3 = u^2 + v^2 and z = (u, v, 1)·M_z, with (u, v) = (zeta_x, zeta_y) / zeta_z.
        u = sp[2]
        v = sp[3]
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
        for i in range(3):
            row[ROW_TRANSFORM + i] = -d_hu[i]
            row[ROW_TRANSFORM + 3 + i] = -d_hv[i]
            row[ROW_TRANSFORM + 6 + i] = d_row_z[i]
        row[ROW_HIT] = 1.0
    else:
        # s2 = filter_inv |pixel - mean|^2; the depth is the centre's.
        d_mean = -2.0 * p.filter_inv * d_s * wp.vec2(fx - mean[0], fy - mean[1])
        row[ROW_MEAN + 0] = d_mean[0]
        row[ROW_MEAN + 1] = d_mean[1]
        row[ROW_DEPTH] = d_z
        row[ROW_SCREEN] = 1.0
    row[ROW_WEIGHT] = w
    row[ROW_T] = T
    row[ROW_SUFFIX] = alpha * c_tilde + (1.0 - alpha) * suffix
    return row


@wp.func
def add_surfel_gradient_row(g: int, row: SurfelGradRow, p: SurfelBlendParams,
                            adj_transforms: wp.array(dtype=wp.mat33), adj_means2d: wp.array(dtype=wp.vec2),
                            adj_depths: wp.array(dtype=float), adj_opacities: wp.array(dtype=float),
                            adj_colors: wp.array(dtype=wp.vec3), adj_normals: wp.array(dtype=wp.vec3)):
    """Adds a gradient row (or a block's sum of rows: ROW_HIT and ROW_SCREEN then count pixels) to the
    surfel's gradients, touching only what can be nonzero."""
    if row[ROW_HIT] > 0.0:
        wp.atomic_add(adj_transforms, g, wp.mat33(
            row[0], row[1], row[2],
            row[3], row[4], row[5],
            row[6], row[7], row[8],
        ))
    if row[ROW_SCREEN] > 0.0:
        wp.atomic_add(adj_means2d, g, wp.vec2(row[ROW_MEAN], row[ROW_MEAN + 1]))
        wp.atomic_add(adj_depths, g, row[ROW_DEPTH])
    wp.atomic_add(adj_opacities, g, row[ROW_OPACITY])
    if p.base.want_color != 0:
        wp.atomic_add(adj_colors, g, wp.vec3(row[ROW_COLOR], row[ROW_COLOR + 1], row[ROW_COLOR + 2]))
    if p.want_normal != 0:
        wp.atomic_add(adj_normals, g, wp.vec3(row[ROW_NORMAL], row[ROW_NORMAL + 1], row[ROW_NORMAL + 2]))
