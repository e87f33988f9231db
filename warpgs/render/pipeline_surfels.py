"""The surfel (2DGS) pipeline on Warp arrays: project -> footprint -> shared tile sort -> blend, and the blend
adjoint. Torch-free; `warpgs.render.surfels` drives it. Tiles and sorting are `pipeline.sort_into_tiles`.

Blending runs as the 3D pipeline's does: block-cooperative kernels (`surfel_blend_gpu.py`) in one launch on
GPUs, per-thread kernels (`surfel_blend.py`) split into tile ranges over a few Python threads on the CPU, each
thread's adjoint accumulating into private gradient buffers that are merged afterwards."""
from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from warpgs.render.cpu_threads import run_threads
from warpgs.render.pipeline_gaussians import (
    Bins,
    Settings,
    Wanted,
    _gradient_buffers,
    _merge_gradient_buffers,
    _tile_launches,
    blend_params,
    choose_blend_kernel,
    sort_into_tiles,
)
from warpgs.kernels import surfel_blend, surfel_blend_gpu, surfel_project, surfel_steps


@dataclass
class SurfelProjected:
    transforms: wp.array
    means2d: wp.array
    depths: wp.array
    normals: wp.array
    colors: wp.array
    valid: wp.array


# Blended images in the order the torch ops return them (and take their gradients): (name, channels, Warp dtype).
IMAGES = (("color", 3, wp.vec3), ("alpha", 1, wp.float32), ("depth", 1, wp.float32), ("inv_depth", 1, wp.float32),
          ("normal", 3, wp.vec3), ("median", 1, wp.float32), ("distortion", 1, wp.float32))


def image_wanted(wanted: "SurfelWanted", name: str) -> bool:
    """Whether image `name` of IMAGES is rendered (alpha always is)."""
    return name == "alpha" or bool(getattr(wanted, name))


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
              inputs=[p.transforms, p.means2d, opacities, p.valid, s.width, s.height, s.tile_size, s.max_sigmas,
                      s.alpha_min],
              outputs=[rects, counts, q_cut], device=dev)
    return sort_into_tiles(rects, counts, p.depths, q_cut, s)


def _blend_inputs(p: SurfelProjected, bins: Bins, opacities, features):
    return [p.transforms, p.means2d, p.depths, opacities, p.colors, p.normals, features, bins.q_cut]


def surfel_blend_params(s: Settings, want: SurfelWanted, first_tile: int) -> surfel_steps.SurfelBlendParams:
    sp = surfel_steps.SurfelBlendParams()
    sp.base = blend_params(s, Wanted(color=want.color, depth=want.depth, inv_depth=want.inv_depth,
                                     num_features=want.num_features), first_tile)
    sp.near, sp.dist_scale = s.near, want.distortion_scale
    sp.want_normal, sp.want_median, sp.want_distortion = int(want.normal), int(want.median), int(want.distortion)
    return sp


def blend_forward(p: SurfelProjected, bins: Bins, opacities, features, s: Settings,
                  want: SurfelWanted) -> SurfelBlended:
    dev = p.means2d.device
    npix = s.width * s.height

    def image(on, dtype):  # every pixel is written; outputs not asked for get a 1-element dummy never touched
        return wp.empty(npix if on else 1, dtype=dtype, device=dev)

    out = SurfelBlended(
        color=image(want.color, wp.vec3), transmittance=image(True, float), alpha=image(True, float),
        depth=image(want.depth, float), inv_depth=image(want.inv_depth, float), normal=image(want.normal, wp.vec3),
        median=image(want.median, float), median_index=image(want.median, wp.int32),
        distortion=image(want.distortion, float), dist_stats=image(want.distortion, wp.vec3),
        # accumulated in place
        features=wp.zeros((npix, want.num_features) if want.num_features else (1, 1), dtype=float, device=dev),
        last=image(True, wp.int32),
    )
    kernel, block_dim, kernel_features = choose_blend_kernel(dev, s, want.num_features, surfel_blend.blend_forward,
                                                             surfel_blend_gpu, backward=False)
    features, out_features = kernel_features(features), kernel_features(out.features)
    head = [bins.tile_start, bins.tile_end, bins.sorted_ids] + _blend_inputs(p, bins, opacities, features)
    outputs = [out.color, out.transmittance, out.alpha, out.depth, out.inv_depth, out.normal, out.median,
               out.median_index, out.distortion, out.dist_stats, out_features, out.last]

    def work(_thread, chunks):  # each chunk writes only its own pixels
        for first, count in chunks:
            wp.launch(kernel, dim=count * s.tile_size**2, inputs=head + [surfel_blend_params(s, want, first)],
                      outputs=outputs, device=dev, block_dim=block_dim)

    run_threads(work, _tile_launches(s, dev), kernels=[kernel], device=dev, block_dim=block_dim)
    return out


def blend_backward(p: SurfelProjected, bins: Bins, opacities, features, s: Settings, want: SurfelWanted,
                   fwd: SurfelBlended, grads: dict):
    """`grads`: upstream Warp arrays keyed color, alpha, depth, inv_depth, normal, median, distortion, features.
    Accumulates into the .grad of the projected arrays, opacities and features (on the CPU, threads other than
    the first accumulate privately and are added in afterwards: Warp's CPU atomics are plain adds)."""
    dev = p.means2d.device
    kernel, block_dim, kernel_features = choose_blend_kernel(dev, s, want.num_features, surfel_blend.blend_backward,
                                                             surfel_blend_gpu, backward=True)
    features, grad_features, adj_features = (kernel_features(a) for a in (features, grads["features"], features.grad))
    targets = [p.transforms.grad, p.means2d.grad, p.depths.grad, opacities.grad, p.colors.grad, p.normals.grad,
               adj_features]
    head = [bins.tile_start, bins.sorted_ids] + _blend_inputs(p, bins, opacities, features)
    tail = ([fwd.transmittance, fwd.last, fwd.median_index, fwd.dist_stats]
            + [grads[k] for k in ("color", "alpha", "depth", "inv_depth", "normal", "median", "distortion")]
            + [grad_features])
    per_thread = _tile_launches(s, dev)
    buffers = _gradient_buffers(targets, len(per_thread))

    def work(thread, chunks):
        for first, count in chunks:
            wp.launch(kernel, dim=count * s.tile_size**2,
                      inputs=head + [surfel_blend_params(s, want, first)] + tail + buffers[thread],
                      device=dev, block_dim=block_dim)

    run_threads(work, per_thread, kernels=[kernel], device=dev, block_dim=block_dim)
    _merge_gradient_buffers(buffers)
