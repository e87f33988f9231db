"""The adjoint of the expected depth, depth = zacc / max(alpha, eps), in one kernel.

The blends accumulate zacc = Σ z_i α_i T_i and write the expected depth beside it as they write each pixel
(blend.write_pixel, surfel_steps.write_surfel_pixel, with BlendParams.depth_eps > 0). Its adjoint here replaces the
seven torch ops of autograd's backward of that division: on a GPU each op is a host dispatch, and at 100k Gaussians
host time is most of a render call. The arithmetic is torch's, operation for operation (div, and clamp_min's gradient
mask alpha >= eps), so both give the same bits.
"""
import warp as wp


@wp.kernel
def normalize_depth_adjoint(
    grad_depth: wp.array(dtype=float),
    zacc: wp.array(dtype=float),
    transmittance: wp.array(dtype=float),  # the blend's final T: alpha = 1 - T, as the blend wrote it
    eps: float,
    has_grad_alpha: int,  # 0: the loss did not use alpha (grad_alpha is not read)
    grad_alpha: wp.array(dtype=float),
    grad_zacc: wp.array(dtype=float),  # out: the blend adjoint's depth upstream
    grad_alpha_total: wp.array(dtype=float),  # out: its alpha upstream (grad_alpha plus the division's share)
):
    p = wp.tid()
    a = 1.0 - transmittance[p]
    c = wp.max(a, eps)
    g = grad_depth[p]
    grad_zacc[p] = g / c
    share = 0.0
    if a >= eps:
        share = -g * ((zacc[p] / c) / c)
    if has_grad_alpha != 0:
        share = grad_alpha[p] + share
    grad_alpha_total[p] = share
