"""Render a primitive model (3D Gaussians or surfels) from one camera: the trainer's single call into the render op.

`render_model` picks `rasterize` or `rasterize_surfels` by the model's kind, passes the model's activated
parameters (`model.render_inputs()`), and asks for exactly the `outputs` given. Everything the trainer, the
evaluation and the CLI render goes through here, so a test can spy on the rasterizer calls in one place.
"""
from __future__ import annotations

from typing import Optional, Sequence

import torch

from warpgs.render.defaults import (DEFAULT_ALPHA_MAX, DEFAULT_ALPHA_MIN, DEFAULT_LOW_PASS, DEFAULT_SURFEL_SCREEN_SIGMA,
                                    DEFAULT_TRANSMITTANCE_MIN)
from warpgs.render.gaussians import OUTPUTS as GAUSSIAN_OUTPUTS
from warpgs.render.gaussians import RenderOutput, rasterize
from warpgs.render.surfels import OUTPUTS as SURFEL_OUTPUTS
from warpgs.render.surfels import rasterize_surfels

OUTPUTS_BY_KIND = {"gaussians": GAUSSIAN_OUTPUTS, "surfels": SURFEL_OUTPUTS}


def check_outputs(kind: str, outputs: Sequence[str], who: str = "outputs") -> None:
    """Raise a clear error when a primitive kind cannot render one of `outputs`."""
    can = OUTPUTS_BY_KIND[kind]
    missing = [o for o in outputs if o not in can]
    if missing:
        other = [k for k, outs in OUTPUTS_BY_KIND.items() if k != kind and all(o in outs for o in missing)]
        hint = f" (model.kind={other[0]} can)" if other else ""
        raise ValueError(f"{who}: model.kind={kind} cannot render {missing}{hint}; it renders {list(can)}")


def surfel_screen_sigma(focal: float, training_focal: Optional[float],
                        base: float = DEFAULT_SURFEL_SCREEN_SIGMA) -> float:
    """The surfels' screen-space fallback width (pixels) for an image of focal length `focal` (pixels) of a model
    trained on images of focal length `training_focal`: `base` px of a training image (2DGS: 1/sqrt(2),
    train.surfel_screen_sigma), in this image's pixels. A fallback fixed in the pixels of every image dilates each
    surfel that is seen smaller than in training (a lower resolution, a wider view, from farther): on fern at 1/4 of
    the training resolution held-out PSNR fell to 21.4 dB against 25.5 with the scaled width (docs/mesh.md).
    training_focal None: `base` (a model without its training cameras)."""
    if not training_focal:
        return base
    return base * float(focal) / float(training_focal)


def gaussian_low_pass(focal: float, training_focal: Optional[float]) -> float:
    """surfel_screen_sigma's twin for 3D Gaussians: the 0.3 px² low-pass of a training image, in this image's px²
    (a fixed 0.3 px² dilates every Gaussian seen smaller than in training; on the built-in scene at 1/4 of the
    training resolution held-out PSNR read 17.3 dB fixed against 25.3 scaled, docs/performance.md)."""
    if not training_focal:
        return DEFAULT_LOW_PASS
    return DEFAULT_LOW_PASS * (float(focal) / float(training_focal)) ** 2


def screen_filter(kind: str, focal: float, training_focal: Optional[float],
                  surfel_sigma: float = DEFAULT_SURFEL_SCREEN_SIGMA) -> dict:
    """render_model's keyword for the kind's screen-space filter at this focal length: {"screen_sigma": ...} for
    surfels (surfel_sigma at the training focal length, train.surfel_screen_sigma), {"low_pass": ...} for 3D
    Gaussians."""
    if kind == "surfels":
        return {"screen_sigma": surfel_screen_sigma(focal, training_focal, surfel_sigma)}
    return {"low_pass": gaussian_low_pass(focal, training_focal)}


def focal_length(K) -> float:
    """sqrt(fx fy) of a 3x3 intrinsics matrix (numpy or torch; a device tensor is read to the host)."""
    return float(K[0][0] * K[1][1]) ** 0.5


def render_model(model, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, *,
                 outputs: Sequence[str] = ("rgb",), background: Optional[torch.Tensor] = None,
                 features: Optional[torch.Tensor] = None, inputs: Optional[dict] = None,
                 track_means2d: bool = False, absgrad: bool = False, near: float = 0.01, far: float = 1e10,
                 tile_size: Optional[int] = None, max_sigmas: float = 0.0, alpha_min: float = DEFAULT_ALPHA_MIN,
                 transmittance_min: float = DEFAULT_TRANSMITTANCE_MIN, alpha_max: float = DEFAULT_ALPHA_MAX,
                 check_inputs: bool = True, deterministic: Optional[bool] = None,
                 screen_sigma: Optional[float] = None, low_pass: Optional[float] = None,
                 speculative_pairs: bool = False) -> RenderOutput:
    """One camera. `inputs` (default: model.render_inputs()) may be edited by the caller, e.g. colours from
    an MLP; `features` [N, C] is rendered when "features" is in outputs. track_means2d (and absgrad, see
    `rasterize`) is honoured for 3D Gaussians only (surfels: `out.means2d` stays None and densification falls back
    to means.grad).
    deterministic: as in `rasterize` (None: the raster option's value). screen_sigma (surfels) and low_pass (3D
    Gaussians): the ops' screen-space filter (None: the op's default; see surfel_screen_sigma, gaussian_low_pass).
    speculative_pairs: see `rasterize` (both kinds)."""
    kind = model.kind
    if kind not in OUTPUTS_BY_KIND:
        raise ValueError(f"model.kind: expected one of {sorted(OUTPUTS_BY_KIND)}, got {kind!r}")
    inputs = dict(model.render_inputs() if inputs is None else inputs)
    if features is not None:
        inputs["features"] = features
    kwargs = dict(viewmat=viewmat, K=K, width=width, height=height, outputs=tuple(outputs), background=background,
                  near=near, far=far, tile_size=tile_size, max_sigmas=max_sigmas, alpha_min=alpha_min,
                  transmittance_min=transmittance_min, alpha_max=alpha_max, check_inputs=check_inputs,
                  deterministic=deterministic, **inputs)
    if kind == "gaussians":
        if low_pass is not None:
            kwargs["low_pass"] = low_pass
        return rasterize(track_means2d=track_means2d, absgrad=absgrad and track_means2d,
                         speculative_pairs=speculative_pairs, **kwargs)
    if screen_sigma is not None:
        kwargs["screen_sigma"] = screen_sigma
    return rasterize_surfels(speculative_pairs=speculative_pairs, **kwargs)
