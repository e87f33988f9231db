"""SSIM's local statistics and its adjoint as a few Warp kernels (CPU and CUDA), for the D-SSIM loss on a GPU.

Images are flat float arrays laid out [B, H, W, C]. The five local means (x, y, x², y², xy) are a separable
Gaussian filter with reflection padding (kornia's, which warpgs.metrics.image.ssim uses): one pass along W, one
along H, each a gather over the window. The adjoint of a reflected filter is not the filter again near the
border (a reflected tap reads an inner pixel twice), so `blur_axis_adjoint` gathers, for every pixel, the
outputs whose taps read it, directly or through a reflection. Torch's version of the same SSIM launches about
a dozen kernels forward and more backward, through a grouped convolution that took 5 ms for a 1080p image on an
H200; these are five launches of memory-bound gathers (the moments formed inside the first filter pass, SSIM
inside the second, the input gradient inside the last adjoint pass).

Only the prediction is differentiated (the target is data): dSSIM/dx = Bᵀa + 2x·Bᵀb + y·Bᵀc, where a, b, c are
the upstream gradient times SSIM's derivatives by the local means of x, x² and xy, and Bᵀ is the filter's adjoint.
"""
from __future__ import annotations

import warp as wp

Moments = wp.types.vector(length=5, dtype=float)  # x, y, x², y², xy (then their local means)
MomentGrads = wp.types.vector(length=3, dtype=float)  # dL/d mean(x), dL/d mean(x²), dL/d mean(xy)


@wp.func
def reflect(j: int, n: int) -> int:
    """Index j of a row of n reflected at both ends without repeating the edge (torch's 'reflect'); |overhang| < n."""
    if j < 0:
        return -j
    if j > n - 1:
        return 2 * (n - 1) - j
    return j


@wp.func
def axis_index(t: int, n: int, stride: int) -> int:
    return (t / stride) % n


@wp.func
def moments_at(x: wp.array(dtype=float), y: wp.array(dtype=float), t: int) -> Moments:
    a = x[t]
    b = y[t]
    return Moments(a, b, a * a, b * b, a * b)


@wp.kernel
def blur_moments_along_w(x: wp.array(dtype=float), y: wp.array(dtype=float), weights: wp.array(dtype=float), n: int,
                         stride: int, out: wp.array(dtype=Moments)):
    """The five moments of each element, filtered along W (length n, element stride `stride`), reflected ends."""
    t = wp.tid()
    i = axis_index(t, n, stride)
    half = weights.shape[0] / 2
    acc = Moments()
    for k in range(weights.shape[0]):
        acc += weights[k] * moments_at(x, y, t + (reflect(i + k - half, n) - i) * stride)
    out[t] = acc


@wp.func
def gather_adjoint(src: wp.array(dtype=MomentGrads), weights: wp.array(dtype=float), t: int, n: int,
                   stride: int) -> MomentGrads:
    """The filter's adjoint at element t: every (output o, tap k) with reflect(o + k - half) == i, its position
    along the axis. Three ways to read i: unreflected (o + k - half == i), through the low end (== -i, for i > 0)
    and through the high end (== 2(n-1) - i, for i < n-1)."""
    i = axis_index(t, n, stride)
    half = weights.shape[0] / 2
    acc = MomentGrads()
    for k in range(weights.shape[0]):
        w = weights[k]
        o = i - k + half
        if o >= 0 and o < n:
            acc += w * src[t + (o - i) * stride]
        if i > 0:
            o = -i - k + half
            if o >= 0 and o < n:
                acc += w * src[t + (o - i) * stride]
        if i < n - 1:
            o = 2 * (n - 1) - i - k + half
            if o >= 0 and o < n:
                acc += w * src[t + (o - i) * stride]
    return acc


@wp.kernel
def blur_adjoint_along_h(src: wp.array(dtype=MomentGrads), weights: wp.array(dtype=float), n: int, stride: int,
                         out: wp.array(dtype=MomentGrads)):
    t = wp.tid()
    out[t] = gather_adjoint(src, weights, t, n, stride)


@wp.kernel
def input_grad_along_w(src: wp.array(dtype=MomentGrads), weights: wp.array(dtype=float), n: int, stride: int,
                       x: wp.array(dtype=float), y: wp.array(dtype=float), out: wp.array(dtype=float)):
    """The adjoint along W, then dL/dx = d mean(x) + 2x d mean(x²) + y d mean(xy) at the element."""
    t = wp.tid()
    a = gather_adjoint(src, weights, t, n, stride)
    out[t] = a[0] + 2.0 * x[t] * a[1] + y[t] * a[2]


@wp.func
def ssim_parts(m: Moments, c1: float, c2: float) -> wp.vec4:
    """A1, A2, B1, B2 of SSIM = A1 A2 / (B1 B2 + eps), in the order of operations of metrics.image.ssim."""
    mu_xy = m[0] * m[1]
    mu_xx = m[0] * m[0]
    mu_yy = m[1] * m[1]
    return wp.vec4(2.0 * mu_xy + c1, 2.0 * (m[4] - mu_xy) + c2, mu_xx + mu_yy + c1,
                   (m[2] - mu_xx) + (m[3] - mu_yy) + c2)


@wp.kernel
def blur_along_h_to_ssim(src: wp.array(dtype=Moments), weights: wp.array(dtype=float), n: int, stride: int,
                         c1: float, c2: float, eps: float, means: wp.array(dtype=Moments), out: wp.array(dtype=float)):
    """The W-filtered moments filtered along H: the local means (kept for the adjoint) and SSIM at the element."""
    t = wp.tid()
    i = axis_index(t, n, stride)
    half = weights.shape[0] / 2
    m = Moments()
    for k in range(weights.shape[0]):
        m += weights[k] * src[t + (reflect(i + k - half, n) - i) * stride]
    means[t] = m
    s = ssim_parts(m, c1, c2)
    out[t] = (s[0] * s[1]) / (s[2] * s[3] + eps)


@wp.kernel
def ssim_map_adjoint(means: wp.array(dtype=Moments), upstream: wp.array(dtype=float), c1: float, c2: float,
                     eps: float, out: wp.array(dtype=MomentGrads)):
    """upstream dL/dSSIM per element -> dL/d of the local means of x, x² and xy."""
    t = wp.tid()
    m = means[t]
    s = ssim_parts(m, c1, c2)
    num = s[0] * s[1]
    den = s[2] * s[3] + eps
    g = upstream[t] / den
    ratio = num / den
    d_mu_x = 2.0 * m[1] * (s[1] - s[0]) - ratio * 2.0 * m[0] * (s[3] - s[2])
    out[t] = MomentGrads(g * d_mu_x, -g * ratio * s[2], g * 2.0 * s[0])
