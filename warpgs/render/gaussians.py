"""The torch op: `rasterize` renders 3D Gaussians with the Warp pipeline (gaussians_fast.py); gradients come from
the hand-written blend adjoint and the projection's generated adjoint. Also the helpers the other ops share.

Conventions follow gsplat so users can swap: OpenCV camera (x right, y down, z forward), world-to-camera
`viewmat`, pixel centres at +0.5, wxyz quaternions (unnormalised), linear scales, opacities in [0, 1].
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, fields
from typing import Optional, Sequence

import torch
import warp as wp

from warpgs.render import pipeline_gaussians as pipeline
from warpgs.render.defaults import (DEFAULT_ALPHA_MAX, DEFAULT_ALPHA_MIN, DEFAULT_LOW_PASS, DEFAULT_SURFEL_SCREEN_SIGMA,
                                    DEFAULT_TRANSMITTANCE_MIN, DEPTH_EPS, LOWEST_TRANSMITTANCE_MIN, alpha_clamp_problem,
                                    choose_tile_size, options_for_call)
from warpgs.render.empty_scene import EmptySceneFunction
from warpgs.render.gaussians_fast import FastRasterizeFunction, run_op
from warpgs.render.validation import (check_finite, check_same_device, check_tensor, checks_before_render,
                                      named_inputs)

OUTPUTS = ("rgb", "alpha", "depth", "inv_depth", "features")


@dataclass
class RenderOutput:
    """Images are [H, W, C] for one camera and [B, H, W, C] for a batch; outputs not asked for are None."""

    rgb: Optional[torch.Tensor] = None
    alpha: Optional[torch.Tensor] = None
    depth: Optional[torch.Tensor] = None  # expected camera z: Σ w_i z_i / alpha
    inv_depth: Optional[torch.Tensor] = None  # accumulated Σ w_i / z_i
    features: Optional[torch.Tensor] = None
    normal: Optional[torch.Tensor] = None  # surfels only: world-space normals facing the camera, Σ w_i n_i
    median_depth: Optional[torch.Tensor] = None  # surfels only: z where accumulated opacity crosses 0.5
    distortion: Optional[torch.Tensor] = None  # surfels only: the 2DGS depth-distortion term
    visible: Optional[torch.Tensor] = None  # [N] (or [B, N]) bool: touched at least one tile
    means2d: Optional[torch.Tensor] = None  # with track_means2d: projected centres; .grad = dL/dmeans2d
    num_intersections: int = 0  # Gaussian-tile pairs (summed over a batch; -1: not read, speculative_pairs)
    # speculative_pairs: a 0-d int32 device tensor, 1 when the render dropped tile pairs (its result is wrong)
    pairs_overflowed: Optional[torch.Tensor] = None
    sent: Optional[torch.Tensor] = None  # render_sharded with track_means2d: [R, N] this rank's splats sent per camera
    seen: Optional[torch.Tensor] = None  # ... and [R, N] those each camera's blend binned (its `visible`)


@functools.lru_cache(maxsize=64)  # a loop renders with the same few: one object each (nothing changes a Settings)
def raster_settings(width, height, near, far, tile_size, max_sigmas, sh_degree, alpha_min,
                    transmittance_min, alpha_max=DEFAULT_ALPHA_MAX, low_pass=DEFAULT_LOW_PASS,
                    screen_sigma=DEFAULT_SURFEL_SCREEN_SIGMA) -> pipeline.Settings:
    """The pipeline's Settings from a render call's arguments (sh_degree None: plain colours)."""
    return pipeline.Settings(width=int(width), height=int(height), near=float(near), far=float(far),
                             tile_size=int(tile_size), max_sigmas=float(max_sigmas),
                             sh_degree=-1 if sh_degree is None else int(sh_degree), alpha_min=float(alpha_min),
                             transmittance_min=float(transmittance_min), alpha_max=float(alpha_max),
                             low_pass=float(low_pass), screen_sigma=float(screen_sigma))


def _zero_grad(t: torch.Tensor) -> torch.Tensor:
    """A contiguous zero gradient buffer for t (zeros_like would copy a transposed input's strides, which the
    contiguous Warp array made from t cannot take as its grad)."""
    return torch.zeros_like(t, memory_format=torch.contiguous_format)


def _to_wp(t: torch.Tensor, dtype, grad: Optional[torch.Tensor] = None):
    t = t.detach().contiguous()
    if grad is not None and t.stride() != grad.stride():
        # torch calls a slice with a size-1 or size-0 dimension contiguous and keeps its strides (a 1-row column
        # slice of packed rows); Warp wants the value and its grad laid out alike.
        t = t.clone(memory_format=torch.contiguous_format)
    return wp.from_torch(t, dtype=dtype, grad=grad)


def set_image_outputs(out: RenderOutput, wanted, color, alpha, zacc, inv, fout, background,
                      depth_normalized: bool = False) -> RenderOutput:
    """Fills the image outputs every primitive kind shares: rgb (over `background`), depth (accumulated z over
    alpha; `depth_normalized`: the op divided already), inverse depth and features, each only if `wanted`."""
    if wanted.color:
        out.rgb = color if background is None else color + (1.0 - alpha) * background
    if wanted.depth:
        out.depth = zacc if depth_normalized else zacc / alpha.clamp_min(DEPTH_EPS)
    if wanted.inv_depth:
        out.inv_depth = inv
    if wanted.num_features:
        out.features = fout
    return out


def blended_images(fwd, settings, wanted) -> tuple:
    """(color, alpha, depth accumulation, inverse depth, features) of a blend forward as torch views [H, W, C]
    (None where not wanted)."""
    H, W = settings.height, settings.width
    color = wp.to_torch(fwd.color).view(-1, 3)[: H * W].view(H, W, 3) if wanted.color else None
    alpha = wp.to_torch(fwd.alpha).view(H, W, 1)
    depth = wp.to_torch(fwd.depth).view(H, W, 1) if wanted.depth else None
    inv_depth = wp.to_torch(fwd.inv_depth).view(H, W, 1) if wanted.inv_depth else None
    feats = wp.to_torch(fwd.features).view(H, W, -1) if wanted.num_features else None
    return color, alpha, depth, inv_depth, feats


def upstream_image_gradients(g_color, g_alpha, g_depth, g_inv, g_feat, settings, wanted, device) -> tuple:
    """The output gradients as the blend adjoint takes them (flat per pixel; outputs that were not computed get a
    1-element dummy the kernel never reads). Call inside the Warp device scope."""
    npix = settings.width * settings.height

    def upstream(g, shape):
        return (torch.zeros(shape, device=device) if g is None else g).contiguous().view(shape)

    gc = wp.from_torch(upstream(g_color, (npix, 3)), dtype=wp.vec3) if wanted.color else wp.zeros(1, dtype=wp.vec3)
    ga = wp.from_torch(upstream(g_alpha, (npix,)))
    gd = wp.from_torch(upstream(g_depth, (npix,))) if wanted.depth else wp.zeros(1, dtype=float)
    gi = wp.from_torch(upstream(g_inv, (npix,))) if wanted.inv_depth else wp.zeros(1, dtype=float)
    nf = wanted.num_features
    gf = wp.from_torch(upstream(g_feat, (npix, nf))) if nf else wp.zeros((1, 1), dtype=float)
    return gc, ga, gd, gi, gf


_INTRINSICS_INDEX: dict = {}  # device -> the flat indices of (fx, fy, cx, cy) in a 3x3 K
_INTRINSICS_SEEN: dict = {}  # id(K) -> (K, its version, its vector), for K tensors that need no gradient
_INTRINSICS_SEEN_SIZE = 64  # cameras remembered (a training loop cycles through its views' K tensors)


def _intrinsics_vector(K: torch.Tensor) -> torch.Tensor:
    """(fx, fy, cx, cy) of K [3,3], differentiable. One gather, and none when the same K tensor comes again
    unchanged (same object, same version counter) and needs no gradient: at 100k Gaussians a GPU render is mostly
    host time, and this was a tenth of what the op did before its first kernel."""
    if K.requires_grad or torch.is_inference_mode_enabled() or K.is_inference():  # no version counter, or not to keep
        return _gather_intrinsics(K)
    seen = _INTRINSICS_SEEN.get(id(K))
    if seen is not None and seen[0] is K and seen[1] == K._version:
        return seen[2]
    vector = _gather_intrinsics(K)
    if len(_INTRINSICS_SEEN) >= _INTRINSICS_SEEN_SIZE:
        _INTRINSICS_SEEN.clear()
    _INTRINSICS_SEEN[id(K)] = (K, K._version, vector)  # holding K keeps id(K) from naming another tensor
    return vector


def _gather_intrinsics(K: torch.Tensor) -> torch.Tensor:
    index = _INTRINSICS_INDEX.get(K.device)
    if index is None:
        with torch.inference_mode(False):  # kept for every later render, inside inference_mode or not
            index = _INTRINSICS_INDEX[K.device] = torch.tensor([0, 4, 2, 5], device=K.device)
    return K.reshape(9).index_select(0, index)


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    *,
    sh_degree: Optional[int] = None,
    features: Optional[torch.Tensor] = None,
    background: Optional[torch.Tensor] = None,
    outputs: Sequence[str] = ("rgb", "alpha"),
    near: float = 0.01,
    far: float = 1e10,
    tile_size: Optional[int] = None,
    max_sigmas: float = 0.0,
    alpha_min: float = DEFAULT_ALPHA_MIN,
    transmittance_min: float = DEFAULT_TRANSMITTANCE_MIN,
    alpha_max: float = DEFAULT_ALPHA_MAX,
    check_inputs: bool = True,
    track_means2d: bool = False,
    absgrad: bool = False,
    deterministic: Optional[bool] = None,
    low_pass: float = DEFAULT_LOW_PASS,
    speculative_pairs: bool = False,
    _means2d_probe: Optional[torch.Tensor] = None,
    _pipeline_checks: bool = False,
) -> RenderOutput:
    """Render N 3D Gaussians from one camera (viewmat [4,4], K [3,3]) or a batch ([B,4,4], [B,3,3]).

    colors: [N,3] plain colours, or SH coefficients [N,K,3] with `sh_degree` d (K >= (d+1)^2; evaluated
    from the camera centre, plus 0.5, clamped at 0). features: [N,C] rendered into `out.features` when
    "features" is in `outputs`. Only the requested outputs are computed.
    track_means2d: also return `out.means2d` [N,2] (or [B,N,2]), the projected centres in pixels, a leaf
    whose `.grad` after backward is dL/dmeans2d (what 3DGS-style densification thresholds).
    absgrad (with track_means2d): `out.means2d.absgrad` [N,2] (or [B,N,2]) after backward holds, per Gaussian, the
    sum over pixels of each pixel's |dL/dmeans2d| per component (AbsGS; gsplat's absgrad): gradients of opposite
    sign from different pixels add instead of cancelling. Differentiate the render once per call, as always.
    tile_size (speed only; None: 8, or 16 for GPU renders of 3D Gaussians autograd will not differentiate of at
    least 0.1 Gaussians a pixel; see render/defaults.py choose_tile_size).
    Accuracy knobs (defaults: the 3DGS rules, exact within them): `max_sigmas` > 0 truncates each footprint at
    that many sigmas; `alpha_min` skips contributions below that alpha; blending stops before transmittance
    would drop under `transmittance_min`. Raising any of them trades accuracy for speed
    (benchmarks/speed_vs_error.py measures how much). `alpha_max` clamps each contribution's alpha (3DGS's 0.99;
    gsplat's 0.999), a modelling choice, not a speed knob.
    deterministic: gradients bit-identical from run to run on GPUs too (a fixed-order sum instead of float atomics
    in the blend adjoint; slower, docs/distributed.md); None: the raster option's value (off unless
    WARPGS_DETERMINISTIC=1 or raster_options(deterministic=True)). The CPU's gradients are deterministic anyway.
    low_pass: px² added to every projected covariance (3DGS's 0.3 by default, gsplat's eps2d); renders of a trained
    model scale it with the image (warpgs.model.rendering.gaussian_low_pass).
    speculative_pairs (one camera, GPU): size the tile-pair sort from this thread's earlier such calls instead of
    waiting for this call's own count, so the call returns without a host sync and the host can queue the loss and
    backward while the GPU projects. A call whose pairs did not fit renders wrongly (some pairs dropped) and says so
    on the device: `out.pairs_overflowed` (0-d int32, 1 then; 0 otherwise, also where the exact path ran: the first
    call, the CPU, input checks, deterministic); the next call's room grows (render/pair_room.py). Meant for loops
    that can discard a step on the device without reading it (the trainer passes it to fused Adam's found_inf);
    `out.num_intersections` is then -1.
    """
    outputs, tile_size = checked_call(OUTPUTS, outputs, means, quats, scales, opacities, colors, viewmat, K, width,
                                      height, sh_degree, features, background, near, far, tile_size, False,
                                      max_sigmas, alpha_min, transmittance_min, scale_dims=3,
                                      track_means2d=track_means2d, alpha_max=alpha_max, low_pass=low_pass)
    pipeline_checks = checks_before_render(check_inputs, _pipeline_checks, means, quats, scales, opacities, colors,
                                           features, viewmat, K, background)
    if absgrad and not (track_means2d or _means2d_probe is not None):
        raise ValueError("absgrad: needs track_means2d=True (it is read from out.means2d.absgrad)")
    if viewmat.dim() == 3:
        probe = means2d_probe(means.new_zeros(viewmat.shape[0], means.shape[0], 2), absgrad) if track_means2d else None
        per_camera = [rasterize(means, quats, scales, opacities, colors, viewmat[b], K[b], width, height,
                                sh_degree=sh_degree, features=features, background=background, outputs=outputs,
                                near=near, far=far, tile_size=tile_size, max_sigmas=max_sigmas, alpha_min=alpha_min,
                                transmittance_min=transmittance_min, alpha_max=alpha_max, check_inputs=False,
                                absgrad=absgrad, deterministic=deterministic, low_pass=low_pass,
                                _means2d_probe=None if probe is None else camera_probe(probe, b),
                                _pipeline_checks=pipeline_checks)
                      for b in range(viewmat.shape[0])]
        out = _stack(per_camera)
        out.means2d = probe
        return out
    probe = _means2d_probe
    if probe is None and track_means2d:
        probe = means2d_probe(means.new_zeros(means.shape[0], 2), absgrad)

    n = means.shape[0]
    coeffs, feats = op_inputs(means, colors, features, outputs)
    settings = raster_settings(width, height, near, far, tile_size, max_sigmas, sh_degree, alpha_min,
                               transmittance_min, alpha_max, low_pass=low_pass)
    wanted = pipeline.Wanted(color="rgb" in outputs, depth="depth" in outputs, inv_depth="inv_depth" in outputs,
                             num_features=feats.shape[1], absgrad=bool(absgrad))
    overflowed = None
    if n > 0:  # returns the expected depth itself (the division runs in a kernel)
        color, alpha, zacc, inv, fout, visible, count, overflowed = run_op(
            FastRasterizeFunction, settings, wanted, options_for_call(deterministic, speculative_pairs), means, quats,
            scales, opacities, coeffs, feats, viewmat, _intrinsics_vector(K), probe,
            (features, K, background) if pipeline_checks else None)
    else:
        H, W = settings.height, settings.width
        shapes = [(H, W, 3) if wanted.color else (0,), (H, W, 1), (H, W, 1) if wanted.depth else (0,),
                  (H, W, 1) if wanted.inv_depth else (0,), (H, W, wanted.num_features) if feats.shape[1] else (0,)]
        color, alpha, zacc, inv, fout = EmptySceneFunction.apply(shapes, means, quats, scales, opacities, coeffs,
                                                                 feats, viewmat, K, probe)
        visible, count = torch.zeros(0, dtype=torch.bool, device=means.device), 0
        overflowed = means.new_zeros((), dtype=torch.int32) if speculative_pairs else None
    out = RenderOutput(alpha=alpha if "alpha" in outputs else None, visible=visible,
                       num_intersections=int(count), means2d=probe, pairs_overflowed=overflowed)
    return set_image_outputs(out, wanted, color, alpha, zacc, inv, fout, background, depth_normalized=True)


def means2d_probe(zeros: torch.Tensor, absgrad: bool) -> torch.Tensor:
    """The leaf whose .grad the 3D op's backward fills with dL/dmeans2d; with absgrad it also carries `.absgrad`,
    a zeroed buffer of its shape the backward adds Σ|dL/dmeans2d| into."""
    probe = zeros.requires_grad_(True)
    if absgrad:
        probe.absgrad = torch.zeros_like(zeros)
    return probe


def camera_probe(probe: torch.Tensor, b: int) -> torch.Tensor:
    """Camera b's row of a batch's probe, with its row of the absgrad buffer when there is one."""
    row = probe[b]
    if hasattr(probe, "absgrad"):
        row.absgrad = probe.absgrad[b]
    return row


def op_inputs(means, colors, features, outputs) -> tuple:
    """(coeffs [N,K,3], feats [N,C]) as the kernels take them: plain colours as degree-0 coefficients, and the
    feature columns only when "features" is rendered (else [N,0])."""
    n = means.shape[0]
    coeffs = colors if colors.dim() == 3 else colors.reshape(n, 1, 3)
    feats = features if (features is not None and "features" in outputs) else means.new_empty(n, 0)
    return coeffs, feats


def _stack(per_camera: list) -> RenderOutput:
    def cat(name):
        vals = [getattr(o, name) for o in per_camera]
        return None if vals[0] is None else torch.stack(vals)

    out = RenderOutput(**{f.name: cat(f.name) for f in fields(RenderOutput)
                          if f.name not in ("num_intersections", "means2d")})
    out.num_intersections = sum(o.num_intersections for o in per_camera)
    return out


def checked_call(known_outputs, outputs, means, quats, scales, opacities, colors, viewmat, K, width, height,
                 sh_degree, features, background, near, far, tile_size, check_values, max_sigmas, alpha_min,
                 transmittance_min, scale_dims, track_means2d=False, alpha_max=DEFAULT_ALPHA_MAX,
                 low_pass=DEFAULT_LOW_PASS, screen_sigma=DEFAULT_SURFEL_SCREEN_SIGMA):
    """What both render ops check before rendering (a ValueError naming the argument), and the settings they
    derive: (outputs as a tuple, the tile size to use)."""
    outputs = tuple(outputs)
    unknown = [o for o in outputs if o not in known_outputs]
    if unknown:
        raise ValueError(f"outputs: unknown {unknown}; choose from {known_outputs}")
    if "features" in outputs and features is None:
        raise ValueError("outputs: 'features' requested but features=None")
    _check_arguments(means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree, features,
                     background, near, far, tile_size, check_values, scale_dims)
    check_blend_knobs(max_sigmas, alpha_min, transmittance_min, alpha_max)
    if not 0.0 <= float(low_pass) < float("inf"):
        raise ValueError(f"low_pass: expected a non-negative number of px², got {low_pass!r}")
    if not 0.0 < float(screen_sigma) < float("inf"):
        raise ValueError(f"screen_sigma: expected a positive number of pixels, got {screen_sigma!r}")
    grad = track_means2d or _needs_grad(means, quats, scales, opacities, colors, features, viewmat, K, background)
    return outputs, choose_tile_size(tile_size, grad, on_gpu=means.device.type == "cuda",
                                     primitives_per_pixel=means.shape[0] / float(width * height), surfels=scale_dims == 2)


def _needs_grad(*tensors) -> bool:
    """Whether autograd will differentiate a render of these inputs."""
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


def check_blend_knobs(max_sigmas, alpha_min, transmittance_min, alpha_max=DEFAULT_ALPHA_MAX) -> None:
    """The blending knobs shared by every primitive kind."""
    if not max_sigmas >= 0.0:
        raise ValueError(f"max_sigmas: expected >= 0 (0: exact footprint), got {max_sigmas}")
    problem = alpha_clamp_problem(alpha_min, alpha_max)
    if problem:
        raise ValueError("%s: %s" % problem)
    if not LOWEST_TRANSMITTANCE_MIN <= transmittance_min < 1.0:  # see raster_defaults
        raise ValueError(f"transmittance_min: expected a value in [{LOWEST_TRANSMITTANCE_MIN:g}, 1), got "
                         f"{transmittance_min} (smaller ones let the transmittance underflow)")


def _check_arguments(means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree, features,
                     background, near, far, tile_size, check_values, scale_dims=3):
    check_tensor("means", means, (None, 3))
    n = means.shape[0]
    check_tensor("quats", quats, (n, 4))
    check_tensor("scales", scales, (n, scale_dims))
    check_tensor("opacities", opacities, (n,))
    if sh_degree is None:
        check_tensor("colors", colors, (n, 3))
    else:
        if not 0 <= int(sh_degree) <= 3:
            raise ValueError(f"sh_degree: expected 0..3, got {sh_degree}")
        check_tensor("colors", colors, (n, None, 3))
        need = (int(sh_degree) + 1) ** 2
        if colors.shape[1] < need:
            raise ValueError(f"colors: sh_degree={sh_degree} needs {need} SH coefficients, got {colors.shape[1]}")
    if features is not None:
        check_tensor("features", features, (n, None))
        if features.shape[1] < 1:
            raise ValueError("features: need at least one channel")
    if viewmat.dim() == 3:
        check_tensor("viewmat", viewmat, (None, 4, 4))
        if viewmat.shape[0] == 0:
            raise ValueError("viewmat: a batch of 0 cameras; give at least one ([B, 4, 4] with B >= 1, or [4, 4])")
        check_tensor("K", K, (viewmat.shape[0], 3, 3))
    else:
        check_tensor("viewmat", viewmat, (4, 4))
        check_tensor("K", K, (3, 3))
    if background is not None:
        check_tensor("background", background, (3,))
    for name, v in (("width", width), ("height", height), ("tile_size", 1 if tile_size is None else tile_size)):
        if int(v) != v or int(v) < 1:
            raise ValueError(f"{name}: expected a positive integer, got {v}")
    if tile_size is not None and tile_size > 32:
        raise ValueError(f"tile_size: at most 32 (a tile is one GPU block of tile_size² threads), got {tile_size}")
    if not (0 < near < far):
        raise ValueError(f"near/far: expected 0 < near < far, got near={near}, far={far}")
    named = named_inputs(means, quats, scales, opacities, colors, features, viewmat, K, background)
    check_same_device(named)
    if check_values:
        check_finite(named, opacities)
