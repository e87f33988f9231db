"""Per-surfel stage for 2D Gaussian surfels (2DGS): the ray-splat transform, camera-facing normal, colour,
and the screen-space footprint used for tile binning.

A surfel is a disk: P(u, v) = centre + s_u t_u u + s_v t_v v, with t_u, t_v the first two columns of its
rotation and t_w (the third) its normal. Its 3x3 transform M maps (u, v, 1) to homogeneous pixel coordinates
(x z, y z, z) = K (R P + t), rows: screen x, screen y, camera z. The blend intersects each pixel's ray with the
surfel plane exactly through M (no affine approximation).

`project_surfels` is branch-free (guarded maths, wp.where) so that Warp's generated adjoint is exact;
`surfel_footprints` is not differentiated.
"""
import warp as wp

from .gaussian_math import clamp_scale, nonzero2, nonzero3, quat_wxyz_to_rotation, rotation_of, translation_of
from .sh import colour_from_sh, eval_sh

COLOR_DIRECT = wp.constant(0)
COLOR_SH = wp.constant(1)
# The screen-space fallback is a Gaussian of standard deviation sigma px around the projected centre: in the
# exponent -s/2 it reads s = |d|^2 / sigma^2 = filter_inv |d|^2. 2DGS's sigma is 1/sqrt(2) px (filter_inv 2, G =
# exp(-|d|^2)); the kernels take filter_inv as an argument (the render op's `screen_sigma`).
# A disk reaching closer than this fraction of its centre depth to the camera plane is bounded through the part of
# it the blend can hit and the screen shows (`clipped_disk_box`): its whole image is a huge ellipse or unbounded.
FRONT_MARGIN = wp.constant(0.01)
WHOLE_SCREEN = wp.constant(1.0e30)


@wp.func
def homogeneous_pixel(v: wp.vec3, fx: float, fy: float, cx: float, cy: float) -> wp.vec3:
    """K v for a camera-space vector v: (fx x + cx z, fy y + cy z, z)."""
    return wp.vec3(fx * v[0] + cx * v[2], fy * v[1] + cy * v[2], v[2])


@wp.func
def project_surfel(
    i: int,
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec2),
    coeffs: wp.array2d(dtype=wp.vec3),  # [N, K]: K=1 plain colours, K>=(d+1)^2 SH
    viewmat: wp.array(dtype=wp.mat44),  # [1] or [N] world -> camera (OpenCV)
    intrinsics: wp.array(dtype=wp.vec4),  # [1] or [N] (fx, fy, cx, cy)
    near: float,
    far: float,
    color_mode: int,
    sh_degree: int,
    transforms: wp.array(dtype=wp.mat33),  # rows: homogeneous x, y, z as linear functions of (u, v, 1)
    means2d: wp.array(dtype=wp.vec2),
    depths: wp.array(dtype=float),  # camera z of the centre (sort key, depth under the screen-space fallback)
    normals: wp.array(dtype=wp.vec3),  # world space, flipped to face the camera
    colors: wp.array(dtype=wp.vec3),
    valid: wp.array(dtype=wp.int32),
):
    """Projects surfel i (the body of both kernels below)."""
    V = viewmat[wp.min(i, viewmat.shape[0] - 1)]  # one camera, or a copy per surfel (kernels/project.py)
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
    zs = wp.max(z, near)  # guarded depth: finite maths for culled surfels

    Rq = quat_wxyz_to_rotation(quats[i])
    s = scales[i]
    tu = wp.vec3(Rq[0, 0], Rq[1, 0], Rq[2, 0])
    tv = wp.vec3(Rq[0, 1], Rq[1, 1], Rq[2, 1])
    tw = wp.vec3(Rq[0, 2], Rq[1, 2], Rq[2, 2])
    col_u = homogeneous_pixel(R * (tu * clamp_scale(s[0])), fx, fy, cx, cy)
    col_v = homogeneous_pixel(R * (tv * clamp_scale(s[1])), fx, fy, cx, cy)
    col_c = homogeneous_pixel(p, fx, fy, cx, cy)
    transforms[i] = wp.mat33(
        col_u[0], col_v[0], col_c[0],
        col_u[1], col_v[1], col_c[1],
        col_u[2], col_v[2], col_c[2],
    )
    means2d[i] = wp.vec2(fx * p[0] / zs + cx, fy * p[1] / zs + cy)
    depths[i] = zs

    campos = -(wp.transpose(R) * t)
    d = mu - campos
    # Face the camera: the flip is piecewise constant, so only t_w carries gradient.
    normals[i] = tw * wp.where(wp.dot(tw, d) > 0.0, -1.0, 1.0)

    if color_mode == COLOR_SH:
        d = d / wp.sqrt(wp.max(wp.dot(d, d), 1.0e-24))
        colors[i] = colour_from_sh(eval_sh(coeffs, i, sh_degree, d))
    else:
        colors[i] = coeffs[i, 0]

    ok = z >= near and z <= far and wp.isfinite(col_u[0] + col_u[1] + col_v[0] + col_v[1] + col_c[0] + col_c[1])
    valid[i] = wp.where(ok, 1, 0)


@wp.kernel
def project_surfels(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec2),
    coeffs: wp.array2d(dtype=wp.vec3),  # [N, K]: K=1 plain colours, K>=(d+1)^2 SH
    viewmat: wp.array(dtype=wp.mat44),  # [1] or [N] world -> camera (OpenCV)
    intrinsics: wp.array(dtype=wp.vec4),  # [1] or [N] (fx, fy, cx, cy)
    near: float,
    far: float,
    color_mode: int,
    sh_degree: int,
    transforms: wp.array(dtype=wp.mat33),  # rows: homogeneous x, y, z as linear functions of (u, v, 1)
    means2d: wp.array(dtype=wp.vec2),
    depths: wp.array(dtype=float),  # camera z of the centre (sort key, depth under the screen-space fallback)
    normals: wp.array(dtype=wp.vec3),  # world space, flipped to face the camera
    colors: wp.array(dtype=wp.vec3),
    valid: wp.array(dtype=wp.int32),
):
    project_surfel(wp.tid(), means, quats, scales, coeffs, viewmat, intrinsics, near, far, color_mode, sh_degree,
                   transforms, means2d, depths, normals, colors, valid)


@wp.func
def surfel_reached(g_transform: wp.mat33, g_mean2d: wp.vec2, g_depth: float, g_normal: wp.vec3,
                   g_color: wp.vec3) -> bool:
    """Whether a surfel has any upstream gradient."""
    return (nonzero3(g_transform[0]) or nonzero3(g_transform[1]) or nonzero3(g_transform[2]) or nonzero2(g_mean2d)
            or g_depth != 0.0 or nonzero3(g_normal) or nonzero3(g_color))


@wp.kernel
def project_surfels_reached(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec2),
    coeffs: wp.array2d(dtype=wp.vec3),  # [N, K]: K=1 plain colours, K>=(d+1)^2 SH
    viewmat: wp.array(dtype=wp.mat44),  # [1] or [N] world -> camera (OpenCV)
    intrinsics: wp.array(dtype=wp.vec4),  # [1] or [N] (fx, fy, cx, cy)
    near: float,
    far: float,
    color_mode: int,
    sh_degree: int,
    transforms: wp.array(dtype=wp.mat33),  # rows: homogeneous x, y, z as linear functions of (u, v, 1)
    means2d: wp.array(dtype=wp.vec2),
    depths: wp.array(dtype=float),  # camera z of the centre (sort key, depth under the screen-space fallback)
    normals: wp.array(dtype=wp.vec3),  # world space, flipped to face the camera
    colors: wp.array(dtype=wp.vec3),
    valid: wp.array(dtype=wp.int32),
    g_transforms: wp.array(dtype=wp.mat33),  # upstream gradients of the outputs (read only)
    g_means2d: wp.array(dtype=wp.vec2),
    g_depths: wp.array(dtype=float),
    g_normals: wp.array(dtype=wp.vec3),
    g_colors: wp.array(dtype=wp.vec3),
):
    """project_surfels for the surfels with an upstream gradient only: its generated adjoint is the projection's
    adjoint without the replay and SH gradient writes of surfels that reached no pixel (kernels/project.py)."""
    i = wp.tid()
    if surfel_reached(g_transforms[i], g_means2d[i], g_depths[i], g_normals[i], g_colors[i]):
        project_surfel(i, means, quats, scales, coeffs, viewmat, intrinsics, near, far, color_mode, sh_degree,
                       transforms, means2d, depths, normals, colors, valid)


@wp.func
def disk_extent(row: wp.vec3, row_z: wp.vec3, r2: float) -> wp.vec2:
    """(centre, half width) along one screen axis of the image of the disk u^2 + v^2 <= r2.

    Rows are normalised by the centre depth (row_z[2] = 1). The image is the conic whose dual is
    M diag(r2, r2, -1) M^T; its tangent lines x = const solve x^2 D22 - 2 x D02 + D00 = 0. The discriminant
    is expanded with Cauchy-Binet into 2x2 minors, which avoids cancelling large squares.
    """
    d22 = r2 * (row_z[0] * row_z[0] + row_z[1] * row_z[1]) - 1.0  # < 0: disk in front of the camera
    d02 = r2 * (row[0] * row_z[0] + row[1] * row_z[1]) - row[2]
    m01 = row[0] * row_z[1] - row[1] * row_z[0]
    m02 = row[0] - row[2] * row_z[0]
    m12 = row[1] - row[2] * row_z[1]
    disc = r2 * (m02 * m02 + m12 * m12 - r2 * m01 * m01)
    return wp.vec2(d02 / d22, wp.sqrt(wp.max(disc, 0.0)) / (-d22))


@wp.func
def cut_line(k: int, row_x: wp.vec3, row_y: wp.vec3, row_z: wp.vec3, e: float, width: float, height: float) -> wp.vec3:
    """Half-plane k of the region `clipped_disk_box` bounds, as (a, b, c) with a u + b v + c >= 0 inside: k = 0
    depth >= e; 1, 2: screen x >= -1, x <= width + 1; 3, 4: y likewise (x = row_x.p / row_z.p, p = (u, v, 1), and
    the depth is positive there, so each is linear in p)."""
    if k == 0:
        return wp.vec3(row_z[0], row_z[1], row_z[2] - e)
    if k == 1:
        return row_x + row_z
    if k == 2:
        return row_z * (width + 1.0) - row_x
    if k == 3:
        return row_y + row_z
    return row_z * (height + 1.0) - row_y


@wp.func
def grow_box(box: wp.vec4, pu: float, pv: float, r2: float, row_x: wp.vec3, row_y: wp.vec3, row_z: wp.vec3,
             e: float, width: float, height: float) -> wp.vec4:
    """box (x_lo, x_hi, y_lo, y_hi) grown by the image of (pu, pv) if that point lies in the region (within a
    tolerance far above float rounding: a point kept by mistake only widens the box)."""
    rr = wp.sqrt(r2)
    if not (pu * pu + pv * pv <= r2 * 1.0001 + 1.0e-6):
        return box
    for k in range(5):
        L = cut_line(k, row_x, row_y, row_z, e, width, height)
        tol = 1.0e-5 * ((wp.abs(L[0]) + wp.abs(L[1])) * rr + wp.abs(L[2]) + 1.0e-6)
        if L[0] * pu + L[1] * pv + L[2] < -tol:
            return box
    d = wp.max(row_z[0] * pu + row_z[1] * pv + row_z[2], 0.5 * e)
    x = (row_x[0] * pu + row_x[1] * pv + row_x[2]) / d
    y = (row_y[0] * pu + row_y[1] * pv + row_y[2]) / d
    return wp.vec4(wp.min(box[0], x), wp.max(box[1], x), wp.min(box[2], y), wp.max(box[3], y))


@wp.func
def turning_points(row: wp.vec3, row_z: wp.vec3, r: float) -> wp.vec4:
    """The two points (u0, v0, u1, v1) of the circle of radius r where the image coordinate row.p / row_z.p turns
    (d/dtheta = 0: P cos + Q sin = R); the circle's first point twice when it has none."""
    P = row[1] * row_z[2] - row[2] * row_z[1]
    Q = row[2] * row_z[0] - row[0] * row_z[2]
    R = -r * (row[1] * row_z[0] - row[0] * row_z[1])
    rho = wp.sqrt(P * P + Q * Q)
    if not (rho > 0.0):
        return wp.vec4(r, 0.0, r, 0.0)
    base = wp.atan2(Q, P)
    half = wp.acos(wp.clamp(R / rho, -1.0, 1.0))
    return wp.vec4(r * wp.cos(base + half), r * wp.sin(base + half), r * wp.cos(base - half), r * wp.sin(base - half))


@wp.func
def clipped_disk_box(row_x: wp.vec3, row_y: wp.vec3, row_z: wp.vec3, r2: float, e: float, width: int,
                     height: int) -> wp.vec4:
    """(x_lo, x_hi, y_lo, y_hi) of the image of the part of the disk u^2 + v^2 <= r2 the blend can hit and the
    screen shows: at depth >= e (rows normalised by the centre depth, so e = near / centre depth) and projecting
    into [-1, width + 1] x [-1, height + 1]; for a disk whose whole image is unbounded (it reaches the camera plane)
    or ill-conditioned. That part is the disk cut by five half-planes (the depth is positive on it, so the screen's
    edges are lines in (u, v)), a convex set, and each screen coordinate is linear-fractional on it, so its extremes
    lie at corners of the set (where two cuts, or a cut and the circle, meet) or where the circle's image turns.
    An empty box (lo > hi) when no such point exists: nothing of the disk is on the screen."""
    W = float(width)
    Hf = float(height)
    r = wp.sqrt(r2)
    big = float(WHOLE_SCREEN)
    box = wp.vec4(big, -big, big, -big)
    tx = turning_points(row_x, row_z, r)
    ty = turning_points(row_y, row_z, r)
    box = grow_box(box, tx[0], tx[1], r2, row_x, row_y, row_z, e, W, Hf)
    box = grow_box(box, tx[2], tx[3], r2, row_x, row_y, row_z, e, W, Hf)
    box = grow_box(box, ty[0], ty[1], r2, row_x, row_y, row_z, e, W, Hf)
    box = grow_box(box, ty[2], ty[3], r2, row_x, row_y, row_z, e, W, Hf)
    for i in range(5):
        A = cut_line(i, row_x, row_y, row_z, e, W, Hf)
        g2 = A[0] * A[0] + A[1] * A[1]
        if g2 > 0.0:  # where cut i meets the circle
            rest = r2 - A[2] * A[2] / g2
            if rest >= 0.0:
                h = wp.sqrt(rest / g2)
                fu = -A[0] * A[2] / g2
                fv = -A[1] * A[2] / g2
                box = grow_box(box, fu - h * A[1], fv + h * A[0], r2, row_x, row_y, row_z, e, W, Hf)
                box = grow_box(box, fu + h * A[1], fv - h * A[0], r2, row_x, row_y, row_z, e, W, Hf)
        for j in range(i + 1, 5):  # where cuts i and j meet
            B = cut_line(j, row_x, row_y, row_z, e, W, Hf)
            det = A[0] * B[1] - B[0] * A[1]
            if det != 0.0:
                box = grow_box(box, (A[1] * B[2] - B[1] * A[2]) / det, (B[0] * A[2] - A[0] * B[2]) / det, r2,
                               row_x, row_y, row_z, e, W, Hf)
    if box[0] > box[1] or box[2] > box[3]:
        return box
    # Generous like disk_extent's callers: float rounding in the blend never finds a pixel outside.
    px = 0.001 * (box[1] - box[0]) + 1.0e-4 * (wp.abs(box[0]) + wp.abs(box[1])) + 0.05
    py = 0.001 * (box[3] - box[2]) + 1.0e-4 * (wp.abs(box[2]) + wp.abs(box[3])) + 0.05
    return wp.vec4(box[0] - px, box[1] + px, box[2] - py, box[3] + py)


@wp.func
def pixel_span(lo: float, hi: float, size: int) -> wp.vec2i:
    """First and last pixel index whose centre (i + 0.5) lies in [lo, hi], clamped to the image."""
    a = wp.clamp(lo - 0.5, -1.0, float(size) + 1.0)  # clamp in float: huge extents cannot overflow int
    b = wp.clamp(hi - 0.5, -1.0, float(size) + 1.0)
    return wp.vec2i(wp.max(int(wp.ceil(a)), 0), wp.min(int(wp.floor(b)), size - 1))


@wp.kernel
def surfel_footprints(
    transforms: wp.array(dtype=wp.mat33),
    means2d: wp.array(dtype=wp.vec2),
    opacities: wp.array(dtype=float),
    valid: wp.array(dtype=wp.int32),
    filter_inv: float,  # 1 / sigma^2 of the screen-space fallback
    near: float,  # the blend's: ray hits closer than this are misses
    width: int,
    height: int,
    tile_size: int,
    max_sigmas: float,
    alpha_min: float,  # the blending's alpha threshold
    rects: wp.array(dtype=wp.vec4i),  # tile x0, y0, x1, y1 (inclusive)
    counts: wp.array(dtype=wp.int32),
    q_cut: wp.array(dtype=float),  # blending skips a pixel with min(s3, s2) beyond this without an exp()
):
    """Tiles holding a pixel that can receive alpha >= alpha_min: G = exp(-min(s3, s2)/2) with s3 = u^2 + v^2
    on the disk and s2 the screen-space fallback, so the footprint is the union of the disk's image with
    u^2 + v^2 <= q_max and the circle s2 <= q_max, q_max = 2 ln(o / alpha_min). Tile size does not change the
    image."""
    i = wp.tid()
    counts[i] = 0
    q_cut[i] = 0.0
    rects[i] = wp.vec4i(0, 0, -1, -1)
    o = opacities[i]
    if valid[i] == 0 or o < alpha_min:
        return
    q_alpha = 2.0 * wp.log(o / alpha_min)
    q_max = q_alpha
    if max_sigmas > 0.0:
        q_max = wp.min(q_max, max_sigmas * max_sigmas)
    # As for 3D Gaussians: a hair generous (the exact alpha test still runs), exact under a max_sigmas cut.
    q_cut[i] = q_max * 1.0001 + 1.0e-4
    if max_sigmas > 0.0 and q_max < q_alpha:
        q_cut[i] = q_max

    M = transforms[i]
    inv_z = 1.0 / M[2, 2]  # centre depth >= near > 0 for valid surfels
    row_x = M[0] * inv_z
    row_y = M[1] * inv_z
    row_z = M[2] * inv_z
    ex = disk_extent(row_x, row_z, q_max)
    ey = disk_extent(row_y, row_z, q_max)
    # Slightly generous so that float rounding in the blend never finds a pixel outside.
    hx = ex[1] * 1.001 + 0.05
    hy = ey[1] * 1.001 + 0.05
    x_lo = ex[0] - hx
    x_hi = ex[0] + hx
    y_lo = ey[0] - hy
    y_hi = ey[0] + hy
    reach = FRONT_MARGIN - 1.0 + q_max * (row_z[0] * row_z[0] + row_z[1] * row_z[1])
    if reach >= 0.0:  # near the camera plane or across it: the part in front of `near` and on the screen
        e = near * inv_z
        r2 = q_max * 1.0001 + 1.0e-4
        box = clipped_disk_box(row_x, row_y, row_z, r2, e, width, height)
        x_lo = box[0]
        x_hi = box[1]
        y_lo = box[2]
        y_hi = box[3]
    if not (wp.isfinite(x_lo) and wp.isfinite(x_hi) and wp.isfinite(y_lo) and wp.isfinite(y_hi)):
        x_lo = -WHOLE_SCREEN
        x_hi = WHOLE_SCREEN
        y_lo = -WHOLE_SCREEN
        y_hi = WHOLE_SCREEN

    m = means2d[i]
    r_screen = wp.sqrt(q_max / filter_inv) * 1.001 + 0.05
    x_lo = wp.min(x_lo, m[0] - r_screen)
    x_hi = wp.max(x_hi, m[0] + r_screen)
    y_lo = wp.min(y_lo, m[1] - r_screen)
    y_hi = wp.max(y_hi, m[1] + r_screen)

    sx = pixel_span(x_lo, x_hi, width)
    sy = pixel_span(y_lo, y_hi, height)
    if sx[0] > sx[1] or sy[0] > sy[1]:
        return
    tx0 = sx[0] / tile_size
    tx1 = sx[1] / tile_size
    ty0 = sy[0] / tile_size
    ty1 = sy[1] / tile_size
    rects[i] = wp.vec4i(tx0, ty0, tx1, ty1)
    counts[i] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
