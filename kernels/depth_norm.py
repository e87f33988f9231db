"""Expected depth from the blend's accumulated depth: depth = zacc / max(alpha, eps), and its adjoint. The 3D
blend writes the division itself as it writes each pixel (blend.write_pixel, BlendParams.depth_eps); the surfel
pipeline still launches `normalize_depth` after its blend.

The blend writes Σ z_i α_i T_i (zacc) and alpha = 1 - T_final per pixel; the depth image is their ratio. Doing
the division in one kernel (and its adjoint in one more) replaces the two torch ops of the forward and the seven
of their autograd backward: on a GPU each op is a host dispatch, and at 100k Gaussians host time is most of a
render call. The arithmetic is torch's, operation for operation (div, and clamp_min's gradient mask alpha >= eps),
so both give the same bits.
"""
import warp as wp


@wp.kernel
def normalize_depth(
    zacc: wp.array(dtype=float),
    alpha: wp.array(dtype=float),
    eps: float,
    depth: wp.array(dtype=float),
):
    p = wp.tid()
    depth[p] = zacc[p] / wp.max(alpha[p], eps)


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
