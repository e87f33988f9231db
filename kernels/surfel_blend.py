"""Surfel blending, one thread per pixel (what the CPU runs): the front-to-back forward and its hand-written
back-to-front adjoint, built from the per-pixel steps of `surfel_steps.py` (the maths are described there).
`surfel_blend_gpu.py` has the block-cooperative versions GPUs run."""
import warp as wp

from .blend import thread_pixel
from .surfel_steps import (
    ROW_SUFFIX,
    ROW_T,
    ROW_WEIGHT,
    SurfelBlendParams,
    add_surfel_gradient_row,
    blend_alpha,
    blend_surfel,
    load_pixel_grads,
    new_surfel_state,
    saturates,
    splat_point,
    surfel_pixel_gradient,
    write_surfel_pixel,
)

# The blend adjoint is hand-written (blend_backward): Warp's generated adjoints are never used, so skip them.
wp.set_module_options({"enable_backward": False})


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
    q_cut: wp.array(dtype=float),
    p: SurfelBlendParams,
    out_color: wp.array(dtype=wp.vec3),
    out_transmittance: wp.array(dtype=float),
    out_alpha: wp.array(dtype=float),
    out_depth: wp.array(dtype=float),
    out_expected_depth: wp.array(dtype=float),
    out_inv_depth: wp.array(dtype=float),
    out_normal: wp.array(dtype=wp.vec3),
    out_median: wp.array(dtype=float),
    out_median_index: wp.array(dtype=wp.int32),
    out_distortion: wp.array(dtype=float),
    out_dist_stats: wp.array(dtype=wp.vec3),  # (m_ref, S1, S2) for the adjoint
    out_features: wp.array2d(dtype=float),
    out_last: wp.array(dtype=wp.int32),
):
    """One thread per pixel (CPU)."""
    inside, pix, tile, fx, fy = thread_pixel(wp.tid(), p.base)
    if not inside:
        return
    start = tile_start[tile]
    end = tile_end[tile]

    st = new_surfel_state(start)
    for k in range(start, end):
        g = sorted_ids[k]
        sp = splat_point(transforms[g], means2d[g], depths[g], fx, fy, p.near, p.filter_inv)
        if sp[0] > q_cut[g]:  # outside the footprint: alpha would be < alpha_min, skip the exp()
            continue
        alpha = blend_alpha(opacities[g], wp.exp(-0.5 * sp[0]), p.base.alpha_max)
        if alpha < p.base.alpha_min:
            continue
        if saturates(st.T, alpha, p.base.t_min):
            break
        for c in range(p.base.num_features):
            out_features[pix, c] = out_features[pix, c] + alpha * st.T * features[g, c]
        st = blend_surfel(st, k, alpha, sp[1], colors[g], normals[g], p)
    write_surfel_pixel(st, pix, p, out_color, out_transmittance, out_alpha, out_depth, out_expected_depth,
                       out_inv_depth, out_normal, out_median, out_median_index, out_distortion, out_dist_stats,
                       out_last)


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
    q_cut: wp.array(dtype=float),
    p: SurfelBlendParams,
    transmittance: wp.array(dtype=float),
    last_index: wp.array(dtype=wp.int32),
    median_index: wp.array(dtype=wp.int32),
    dist_stats: wp.array(dtype=wp.vec3),
    zacc: wp.array(dtype=float),  # the forward's depth accumulation (read when p.base.depth_eps > 0)
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
    """The blending adjoint, one thread per pixel, adding each pixel's gradient to global memory (CPU)."""
    inside, pix, tile, fx, fy = thread_pixel(wp.tid(), p.base)
    if not inside:
        return
    start = tile_start[tile]
    pg = load_pixel_grads(pix, p, transmittance, median_index, dist_stats, zacc, grad_color, grad_alpha, grad_depth,
                          grad_inv_depth, grad_normal, grad_median, grad_distortion)
    T = transmittance[pix]  # transmittance behind the current surfel, walking back to front
    suffix = float(0.0)  # Σ_channels g·(what is seen behind the current surfel), per unit transmittance
    k = last_index[pix]
    while k > start:
        k -= 1
        g = sorted_ids[k]
        M = transforms[g]
        mean = means2d[g]
        sp = splat_point(M, mean, depths[g], fx, fy, p.near, p.filter_inv)
        if sp[0] > q_cut[g]:
            continue
        G = wp.exp(-0.5 * sp[0])
        o = opacities[g]
        if blend_alpha(o, G, p.base.alpha_max) < p.base.alpha_min:
            continue
        feature_dot = float(0.0)
        for c in range(p.base.num_features):
            feature_dot += features[g, c] * grad_features[pix, c]
        row = surfel_pixel_gradient(k, sp, M, mean, o, G, colors[g], normals[g], fx, fy, T, suffix, pg, feature_dot,
                                    p)
        T = row[ROW_T]
        suffix = row[ROW_SUFFIX]
        add_surfel_gradient_row(g, row, p, adj_transforms, adj_means2d, adj_depths, adj_opacities, adj_colors,
                                adj_normals)
        for c in range(p.base.num_features):
            wp.atomic_add(adj_features, g, c, row[ROW_WEIGHT] * grad_features[pix, c])
