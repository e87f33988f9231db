"""The surfel (2DGS) pipeline on Warp arrays: project -> footprint -> shared tile sort -> blend, and the blend
adjoint. Torch-free; `warpgs.render_surfels` drives it. Tiles and sorting are `pipeline.sort_into_tiles`."""
from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from warpgs.pipeline import Bins, Settings, sort_into_tiles
from warpgs.kernels import surfel_blend, surfel_project


@dataclass
class SurfelProjected:
    transforms: wp.array
    means2d: wp.array
    depths: wp.array
    normals: wp.array
    colors: wp.array
    valid: wp.array


@dataclass
class SurfelWanted:
    color: bool
    depth: bool
    inv_depth: bool
    normal: bool
    median: bool
    distortion: bool
    num_features: int
    distortion_scale: float  # m = -distortion_scale / z in the distortion term


@dataclass
class SurfelBlended:
    color: wp.array
    transmittance: wp.array
    alpha: wp.array
    depth: wp.array
    inv_depth: wp.array
    normal: wp.array
    median: wp.array
    median_index: wp.array
    distortion: wp.array
    dist_stats: wp.array
    features: wp.array
    last: wp.array


def project_surfels(means, quats, scales, coeffs, viewmat, intrinsics, s: Settings, requires_grad: bool):
    n = means.shape[0]
    dev = means.device

    def buf(dtype):
        return wp.zeros(n, dtype=dtype, device=dev, requires_grad=requires_grad)

    out = SurfelProjected(transforms=buf(wp.mat33), means2d=buf(wp.vec2), depths=buf(float), normals=buf(wp.vec3),
                          colors=buf(wp.vec3), valid=wp.zeros(n, dtype=wp.int32, device=dev))
    color_mode = surfel_project.COLOR_SH if s.sh_degree >= 0 else surfel_project.COLOR_DIRECT
    wp.launch(surfel_project.project_surfels, dim=n,
              inputs=[means, quats, scales, coeffs, viewmat, intrinsics, s.near, s.far, color_mode,
                      max(s.sh_degree, 0)],
              outputs=[out.transforms, out.means2d, out.depths, out.normals, out.colors, out.valid], device=dev)
    return out


def bin_surfels(p: SurfelProjected, opacities, s: Settings) -> Bins:
    n = p.means2d.shape[0]
    dev = p.means2d.device
    counts = wp.zeros(n, dtype=wp.int32, device=dev)
    rects = wp.zeros(n, dtype=wp.vec4i, device=dev)
    q_cut = wp.zeros(n, dtype=float, device=dev)
    wp.launch(surfel_project.surfel_footprints, dim=n,
              inputs=[p.transforms, p.means2d, opacities, p.valid, s.width, s.height, s.tile_size, s.max_sigmas],
              outputs=[rects, counts, q_cut], device=dev)
    return sort_into_tiles(rects, counts, p.depths, q_cut, s)


def _blend_inputs(p: SurfelProjected, bins: Bins, opacities, features, s: Settings, want: SurfelWanted):
    return [p.transforms, p.means2d, p.depths, opacities, p.colors, p.normals, features, s.width, s.height,
            s.tiles_x, s.tile_size, bins.q_cut, s.near, want.distortion_scale, int(want.color), int(want.depth),
            int(want.inv_depth), int(want.normal), int(want.median), int(want.distortion), want.num_features]


def blend_forward(p: SurfelProjected, bins: Bins, opacities, features, s: Settings,
                  want: SurfelWanted) -> SurfelBlended:
    dev = p.means2d.device
    npix = s.width * s.height

    def image(on, dtype):  # outputs not asked for get a 1-element dummy the kernel never touches
        return wp.zeros(npix if on else 1, dtype=dtype, device=dev)

    out = SurfelBlended(
        color=image(want.color, wp.vec3), transmittance=image(True, float), alpha=image(True, float),
        depth=image(want.depth, float), inv_depth=image(want.inv_depth, float), normal=image(want.normal, wp.vec3),
        median=image(want.median, float), median_index=image(want.median, wp.int32),
        distortion=image(want.distortion, float), dist_stats=image(want.distortion, wp.vec3),
        features=wp.zeros((npix, want.num_features) if want.num_features else (1, 1), dtype=float, device=dev),
        last=image(True, wp.int32),
    )
    wp.launch(surfel_blend.blend_forward, dim=s.num_tiles * s.tile_size**2,
              inputs=[bins.tile_start, bins.tile_end, bins.sorted_ids]
              + _blend_inputs(p, bins, opacities, features, s, want),
              outputs=[out.color, out.transmittance, out.alpha, out.depth, out.inv_depth, out.normal, out.median,
                       out.median_index, out.distortion, out.dist_stats, out.features, out.last],
              device=dev)
    return out


def blend_backward(p: SurfelProjected, bins: Bins, opacities, features, s: Settings, want: SurfelWanted,
                   fwd: SurfelBlended, grads: dict):
    """`grads`: upstream Warp arrays keyed color, alpha, depth, inv_depth, normal, median, distortion, features.
    Accumulates into the .grad of the projected arrays, opacities and features."""
    wp.launch(surfel_blend.blend_backward, dim=s.num_tiles * s.tile_size**2,
              inputs=[bins.tile_start, bins.sorted_ids] + _blend_inputs(p, bins, opacities, features, s, want)
              + [fwd.transmittance, fwd.last, fwd.median_index, fwd.dist_stats]
              + [grads[k] for k in ("color", "alpha", "depth", "inv_depth", "normal", "median", "distortion",
                                    "features")]
              + [p.transforms.grad, p.means2d.grad, p.depths.grad, opacities.grad, p.colors.grad, p.normals.grad,
                 features.grad],
              device=p.means2d.device)
