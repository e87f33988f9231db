"""The torch op `rasterize_surfels`: renders 2D Gaussian surfels (2DGS) with the Warp pipeline (`surfels_fast`:
workspace, recorded launches); gradients come from the hand-written blend adjoint and the projection's generated
adjoint.

Same conventions and arguments as `rasterize`, with scales [N, 2] (the disk's two axes; the quaternion's
third rotation column is the normal) and the extra outputs normal, median_depth and distortion.
"""
from __future__ import annotations

from typing import Optional, Sequence

import torch
import warp as wp

from warpgs.render import fast_pipeline_surfels as fast
from warpgs.render.defaults import (DEFAULT_ALPHA_MAX, DEFAULT_ALPHA_MIN, DEFAULT_SURFEL_SCREEN_SIGMA,
                                    DEFAULT_TILE_SIZE, DEFAULT_TRANSMITTANCE_MIN, options_for_call)
from warpgs.render.empty_scene import EmptySceneFunction
from warpgs.render.fast_pipeline import feature_layout
from warpgs.render.fast_pipeline_surfels import IMAGES, SurfelWanted, image_wanted
from warpgs.render.gaussians import (RenderOutput, _intrinsics_vector, _stack, _to_wp, checked_call, raster_settings,
                                     op_inputs, set_image_outputs)
from warpgs.render.device_state import device_state
from warpgs.render.gaussians_fast import _features_arg, run_op
from warpgs.render.pipeline_gaussians import Settings
from warpgs.render.validation import checks_before_render
from warpgs.render.surfels_fast import FastSurfelsFunction

OUTPUTS = ("rgb", "alpha", "depth", "inv_depth", "normal", "median_depth", "distortion", "features")
# 2DGS measures distortion on NDC depth m = f/(f-n) (1 - n/z) with these fixed planes; the constant part
# cancels in the pairwise differences, leaving m = -(f n / (f - n)) / z.
DISTORTION_NEAR = 0.2
DISTORTION_FAR = 100.0
DISTORTION_SCALE = DISTORTION_FAR * DISTORTION_NEAR / (DISTORTION_FAR - DISTORTION_NEAR)



def rasterize_surfels(
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
    deterministic: Optional[bool] = None,
    screen_sigma: float = DEFAULT_SURFEL_SCREEN_SIGMA,
    speculative_pairs: bool = False,
    _pipeline_checks: bool = False,
) -> RenderOutput:
    """Render N 2D Gaussian surfels from one camera (viewmat [4,4], K [3,3]) or a batch ([B,4,4], [B,3,3]).

    scales: [N,2] linear disk scales; the quaternion's rotation has the disk axes as its first two columns
    and the normal as its third. colors/sh_degree/features/background as in `rasterize`.
    outputs: any of rgb, alpha, depth (Σ w z / alpha, z the ray-surfel hit depth), inv_depth (Σ w / z),
    normal (Σ w n, world space, each normal facing the camera), median_depth, distortion, features.
    Only the requested outputs are computed. tile_size, max_sigmas / alpha_min / transmittance_min / alpha_max,
    deterministic: as in `rasterize`. screen_sigma: the standard deviation in pixels of the screen-space Gaussian
    that stands in for a surfel seen edge-on or smaller than a pixel (2DGS's 1/sqrt(2) by default; renders of a
    trained model scale it with the image, warpgs.model.rendering.surfel_screen_sigma). speculative_pairs (one
    camera, GPU): as in `rasterize` (`out.pairs_overflowed`).
    """
    outputs, tile_size = checked_call(OUTPUTS, outputs, means, quats, scales, opacities, colors, viewmat, K, width,
                                      height, sh_degree, features, background, near, far, tile_size, False,
                                      max_sigmas, alpha_min, transmittance_min, scale_dims=2, alpha_max=alpha_max,
                                      screen_sigma=screen_sigma)
    pipeline_checks = checks_before_render(check_inputs, _pipeline_checks, means, quats, scales, opacities, colors,
                                           features, viewmat, K, background)
    if viewmat.dim() == 3:
        per_camera = [rasterize_surfels(means, quats, scales, opacities, colors, viewmat[b], K[b], width, height,
                                        sh_degree=sh_degree, features=features, background=background,
                                        outputs=outputs, near=near, far=far, tile_size=tile_size,
                                        max_sigmas=max_sigmas, alpha_min=alpha_min,
                                        transmittance_min=transmittance_min, alpha_max=alpha_max,
                                        check_inputs=False, deterministic=deterministic,
                                        screen_sigma=screen_sigma, _pipeline_checks=pipeline_checks)
                      for b in range(viewmat.shape[0])]
        return _stack(per_camera)

    n = means.shape[0]
    coeffs, feats = op_inputs(means, colors, features, outputs)
    settings = raster_settings(width, height, near, far, tile_size, max_sigmas, sh_degree, alpha_min,
                               transmittance_min, alpha_max, screen_sigma=screen_sigma)
    wanted = SurfelWanted(
        color="rgb" in outputs, depth="depth" in outputs, inv_depth="inv_depth" in outputs,
        normal="normal" in outputs, median="median_depth" in outputs, distortion="distortion" in outputs,
        num_features=feats.shape[1], distortion_scale=DISTORTION_SCALE)
    if n > 0:  # returns the expected depth itself (the division runs in a kernel)
        color, alpha, zacc, inv, normal, median, distortion, fout, visible, count, overflowed = run_op(
            FastSurfelsFunction, settings, wanted, options_for_call(deterministic, speculative_pairs), means, quats,
            scales, opacities, coeffs, feats, viewmat, _intrinsics_vector(K),
            (features, K, background) if pipeline_checks else None)
    else:
        H, W = settings.height, settings.width
        shapes = [(H, W, c) if image_wanted(wanted, name) else (0,) for name, c, _ in IMAGES]
        shapes.append((H, W, wanted.num_features) if wanted.num_features else (0,))
        color, alpha, zacc, inv, normal, median, distortion, fout = EmptySceneFunction.apply(
            shapes, means, quats, scales, opacities, coeffs, feats, viewmat, K)
        visible, count = torch.zeros(0, dtype=torch.bool, device=means.device), 0
        overflowed = means.new_zeros((), dtype=torch.int32) if speculative_pairs else None
    out = RenderOutput(alpha=alpha if "alpha" in outputs else None, visible=visible, num_intersections=int(count),
                       pairs_overflowed=overflowed)
    set_image_outputs(out, wanted, color, alpha, zacc, inv, fout, background, depth_normalized=True)
    if wanted.normal:
        out.normal = normal
    if wanted.median:
        out.median_depth = median
    if wanted.distortion:
        out.distortion = distortion
    return out


def surfel_work(means, quats, scales, opacities, viewmat, K, width: int, height: int, *, near: float = 0.01,
                far: float = 1e10, tile_size: int = DEFAULT_TILE_SIZE) -> dict:
    """For benchmarks: the work one forward pass does on a single camera (no autograd, alpha only).

    Returns {"evaluations": surfel-pixel evaluations the blending loops perform (each pixel walks its tile's
    list up to its stopping point), "tile_pairs": surfel-tile pairs after binning}.
    """
    n = means.shape[0]
    s = Settings(width=int(width), height=int(height), near=float(near), far=float(far), tile_size=int(tile_size))
    want = SurfelWanted(color=False, depth=False, inv_depth=False, normal=False, median=False, distortion=False,
                        num_features=0, distortion_scale=DISTORTION_SCALE)
    state = device_state(means.device)
    ws = state.ws
    alpha = means.new_empty(s.height * s.width)
    arrays = [_to_wp(t, dtype) for t, dtype in (
        (means, wp.vec3), (quats, wp.vec4), (scales, wp.vec2), (means.new_zeros(n, 1, 3), wp.vec3),
        (viewmat.reshape(1, 4, 4), wp.mat44), (_intrinsics_vector(K).reshape(1, 4), wp.vec4),
        (opacities, wp.float32), (alpha, wp.float32))]
    no_features = _features_arg(None, 0, feature_layout(state.wdev), state)
    outputs = [arrays[7] if name == "alpha" else ws.dummy(dtype) for name, _, dtype in IMAGES] + [no_features,
                                                                                                  ws.dummy(float)]
    with state.scope():
        frame = fast.forward(ws, s, want, arrays[:6], arrays[6], no_features, outputs, None)
        last = state.tensor(frame.last).view(s.height, s.width).long()
        start = state.tensor(frame.tile_start).long()
    ty = torch.arange(s.height, device=last.device) // s.tile_size
    tx = torch.arange(s.width, device=last.device) // s.tile_size
    walked = (last - start[ty[:, None] * s.tiles_x + tx[None, :]]).clamp_min(0)
    return {"evaluations": int(walked.sum().item()), "tile_pairs": frame.total}
