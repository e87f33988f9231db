"""Where a surfel's disk lands on the screen, for its tile footprint (surfel_project.surfel_footprints): the extent of
the image of a disk through one row of its ray-splat transform (`disk_extent`), and, for a disk whose whole image is
unbounded or ill-conditioned (it reaches the camera plane), the box of the part the blend can hit and the screen
shows (`clipped_disk_box`). A row r maps a disk point p = (u, v, 1) to r.p; a screen coordinate is row_x.p / row_z.p.
"""
import warp as wp

WHOLE_SCREEN = wp.constant(1.0e30)  # a footprint bound that covers every tile


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
