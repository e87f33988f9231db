"""The 3D Gaussian render op cut in two at the projected splats, for renders whose primitives do not all live in
one process (model-parallel training: docs/distributed.md). `project_splats` turns 3D Gaussians into the 2D
splats one camera sees; `blend_splats` bins and blends splats gathered from anywhere. Both are torch autograd
ops over the same Warp stages and buffers as `rasterize` (render/splats_fast.py), so
`blend_splats(project_splats(...))` renders and differentiates what `rasterize` does (tests/test_render_splats.py)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import torch

from warpgs.render import pipeline_gaussians as pipeline
from warpgs.render.defaults import (DEFAULT_ALPHA_MAX, DEFAULT_ALPHA_MIN, DEFAULT_TILE_SIZE, DEFAULT_TRANSMITTANCE_MIN,
                                    options_for_call)
from warpgs.render.empty_scene import EmptySceneFunction
from warpgs.render.gaussians import (OUTPUTS, RenderOutput, _intrinsics_vector, check_blend_knobs, checked_call,
                                     raster_settings, set_image_outputs)
from warpgs.render.splats_fast import (COLUMNS, SPLAT_COLUMNS, FastBlendRowsFunction, FastProjectRowsFunction,
                                       column)

# Packed splat rows (pack / unpack, and what ranks exchange): means2d 2, conics 3, cov2d 3, depth 1, colour 3,
# opacity 1, then the features (splats_fast.COLUMNS).
__all__ = ["SPLAT_COLUMNS", "Splats", "blend_rows", "blend_splats", "project_rows", "project_splats"]


@dataclass
class Splats:
    """N projected 3D Gaussians as one camera sees them (rows line up with the primitives they came from).
    cov2d and valid steer binning only and carry no gradient."""

    means2d: torch.Tensor  # [N, 2] pixels
    conics: torch.Tensor  # [N, 3] inverse 2D covariance (a, b, c)
    cov2d: torch.Tensor  # [N, 3]
    depths: torch.Tensor  # [N] camera z
    colors: torch.Tensor  # [N, 3] evaluated colour (SH at this camera)
    valid: torch.Tensor  # [N] bool: in front of the near plane and projectable
    opacities: torch.Tensor  # [N]
    features: torch.Tensor  # [N, C] (C may be 0)

    def pack(self) -> torch.Tensor:
        """[N, 13 + C] float rows, differentiable in every column but cov2d (for exchanging between ranks)."""
        return torch.cat([self.means2d, self.conics, self.cov2d.detach(), self.depths[:, None], self.colors,
                          self.opacities[:, None], self.features], dim=1)

    @staticmethod
    def unpack(rows: torch.Tensor, valid: Optional[torch.Tensor] = None) -> "Splats":
        """The inverse of pack (views of the rows' columns); valid None: every row is valid."""
        if valid is None:
            valid = torch.ones(rows.shape[0], dtype=torch.bool, device=rows.device)
        fields = {name: column(rows, name) for name in COLUMNS}  # the layout splats_fast defines
        fields["cov2d"] = fields["cov2d"].detach()
        return Splats(**fields, valid=valid, features=rows[:, SPLAT_COLUMNS:])

    def select(self, rows: torch.Tensor) -> "Splats":
        return Splats(*(getattr(self, f)[rows] for f in ("means2d", "conics", "cov2d", "depths", "colors", "valid",
                                                          "opacities", "features")))


def project_rows(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *,
                 sh_degree: Optional[int] = None, features: Optional[torch.Tensor] = None, near: float = 0.01,
                 far: float = 1e10) -> Tuple[torch.Tensor, torch.Tensor]:
    """(rows [N, 13 + C], valid [N] bool): the packed splat rows of N 3D Gaussians seen from one camera (viewmat
    [4,4], K [3,3]); arguments as `rasterize`, checked as it checks them. Gradients flow from the rows (all columns
    but cov2d) back to every input."""
    checked_call(OUTPUTS, ("rgb",), means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree,
                 features, None, near, far, None, True, 0.0, DEFAULT_ALPHA_MIN, DEFAULT_TRANSMITTANCE_MIN, scale_dims=3)
    n = means.shape[0]
    coeffs = colors if colors.dim() == 3 else colors.reshape(n, 1, 3)
    settings = raster_settings(width, height, near, far, DEFAULT_TILE_SIZE, 0.0, sh_degree, DEFAULT_ALPHA_MIN,
                               DEFAULT_TRANSMITTANCE_MIN)
    feats = features if features is not None else means.new_zeros(n, 0)
    return FastProjectRowsFunction.apply(settings, means, quats, scales, coeffs, viewmat, _intrinsics_vector(K),
                                         opacities, feats)


def project_splats(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *,
                   sh_degree: Optional[int] = None, features: Optional[torch.Tensor] = None, near: float = 0.01,
                   far: float = 1e10) -> Splats:
    """The splats of N 3D Gaussians seen from one camera: `project_rows` seen as a Splats (views of the rows)."""
    rows, valid = project_rows(means, quats, scales, opacities, colors, viewmat, K, width, height,
                               sh_degree=sh_degree, features=features, near=near, far=far)
    return Splats.unpack(rows, valid)


def blend_rows(rows: torch.Tensor, width: int, height: int, *, background: Optional[torch.Tensor] = None,
               outputs: Sequence[str] = ("rgb", "alpha"), tile_size: Optional[int] = None,
               alpha_min: float = DEFAULT_ALPHA_MIN, transmittance_min: float = DEFAULT_TRANSMITTANCE_MIN,
               alpha_max: float = DEFAULT_ALPHA_MAX) -> RenderOutput:
    """Bin and blend packed splat rows, every one valid (from `project_rows`, possibly gathered from several
    processes), into one image with the outputs of `rasterize`; "features" renders the rows' feature columns."""
    unknown = [o for o in outputs if o not in OUTPUTS]
    if unknown:
        raise ValueError(f"outputs: unknown {unknown}; expected some of {OUTPUTS}")
    check_blend_knobs(0.0, alpha_min, transmittance_min, alpha_max)
    if rows.dim() != 2 or rows.shape[1] < SPLAT_COLUMNS:
        raise ValueError(f"rows: expected [N, {SPLAT_COLUMNS} + C] splat rows, got {list(rows.shape)}")
    num_features = rows.shape[1] - SPLAT_COLUMNS
    if "features" in outputs and num_features == 0:
        raise ValueError("outputs: 'features' asked for, but the splats carry no feature columns")
    nf = num_features if "features" in outputs else 0
    settings = raster_settings(width, height, 0.01, 1e10, tile_size or DEFAULT_TILE_SIZE, 0.0, None, alpha_min,
                               transmittance_min, alpha_max)
    wanted = pipeline.Wanted(color="rgb" in outputs, depth="depth" in outputs, inv_depth="inv_depth" in outputs,
                             num_features=nf)
    if rows.shape[0]:
        color, alpha, depth, inv, fout, visible = FastBlendRowsFunction.apply(
            settings, wanted, options_for_call(None), rows)
    else:  # nothing reaches this camera: the blend of nothing, connected to the (empty) rows
        shapes = [(height, width, c) if want else (0,) for c, want in (
            (3, wanted.color), (1, True), (1, wanted.depth), (1, wanted.inv_depth), (nf, nf))]
        color, alpha, depth, inv, fout = EmptySceneFunction.apply(shapes, rows)
        visible = torch.zeros(0, dtype=torch.bool, device=rows.device)
    out = RenderOutput(alpha=alpha if "alpha" in outputs else None, visible=visible)
    return set_image_outputs(out, wanted, color, alpha, depth, inv, fout, background, depth_normalized=True)


def blend_splats(splats: Splats, width: int, height: int, *, background: Optional[torch.Tensor] = None,
                 outputs: Sequence[str] = ("rgb", "alpha"), tile_size: Optional[int] = None,
                 alpha_min: float = DEFAULT_ALPHA_MIN,
                 transmittance_min: float = DEFAULT_TRANSMITTANCE_MIN,
                 alpha_max: float = DEFAULT_ALPHA_MAX) -> RenderOutput:
    """`blend_rows` of splats (from `project_splats`, possibly gathered from several processes). Invalid rows are
    dropped first; `out.visible` is over the valid rows."""
    if splats.means2d.dim() != 2 or splats.means2d.shape[1] != 2:
        raise ValueError(f"splats.means2d: expected [N, 2], got {list(splats.means2d.shape)}")
    if not bool(splats.valid.all()):
        splats = splats.select(splats.valid)
    return blend_rows(splats.pack(), width, height, background=background, outputs=outputs, tile_size=tile_size,
                      alpha_min=alpha_min, transmittance_min=transmittance_min, alpha_max=alpha_max)
