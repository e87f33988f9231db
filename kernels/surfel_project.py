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
from .surfel_disk_image import WHOLE_SCREEN, clipped_disk_box, disk_extent

COLOR_DIRECT = wp.constant(0)
COLOR_SH = wp.constant(1)
# The screen-space fallback is a Gaussian of standard deviation sigma px around the projected centre: in the
# exponent -s/2 it reads s = |d|^2 / sigma^2 = filter_inv |d|^2. 2DGS's sigma is 1/sqrt(2) px (filter_inv 2, G =
# exp(-|d|^2)); the kernels take filter_inv as an argument (the render op's `screen_sigma`).
# A disk reaching closer than this fraction of its centre depth to the camera plane is bounded through the part of
# it the blend can hit and the screen shows (`clipped_disk_box`): its whole image is a huge ellipse or unbounded.
FRONT_MARGIN = wp.constant(0.01)


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
