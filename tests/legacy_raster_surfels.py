"""The per-call surfel op the fast one (render/surfels_fast.py) replaced, kept as the tests' oracle: the surfel
kernels driven the simple way (per-call arrays, a wp.Tape for the projection's adjoint, the blend adjoint recorded on
it; binning and sorting are `pipeline_gaussians.bin_into_tiles`), so on the CPU the fast path must give the same
images and gradients to the last bit. `rasterize_surfels_legacy` takes the arguments of `rasterize_surfels` that the
tests use."""
from __future__ import annotations

from dataclasses import dataclass

import torch
import warp as wp

from warpgs.kernels import surfel_blend, surfel_blend_gpu, surfel_project
from warpgs.render.cpu_threads import run_threads
from warpgs.render.defaults import DEFAULT_ALPHA_MAX, DEFAULT_ALPHA_MIN, DEFAULT_TRANSMITTANCE_MIN, choose_tile_size
from warpgs.render.fast_pipeline_surfels import IMAGES, SurfelWanted, image_wanted, surfel_blend_params
from warpgs.render.gaussians import (RenderOutput, _intrinsics_vector, _stack, raster_settings, op_inputs,
                                     set_image_outputs)
from warpgs.render.torch_streams import on_torch_stream
from warpgs.render.pipeline_gaussians import (Bins, Settings, _gradient_buffers, _merge_gradient_buffers,
                                              _tile_launches, bin_into_tiles, choose_blend_kernel)
from warpgs.render.surfels import DISTORTION_SCALE

from legacy_raster import warp_inputs


@dataclass
class SurfelProjected:
    transforms: wp.array
    means2d: wp.array
    depths: wp.array
    normals: wp.array
    colors: wp.array
    valid: wp.array


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
    filter_inv = 1.0 / (s.screen_sigma * s.screen_sigma)
    return bin_into_tiles(surfel_project.surfel_footprints,
                          [p.transforms, p.means2d, opacities, p.valid, filter_inv, s.near], p.depths, s)


def _blend_inputs(p: SurfelProjected, bins: Bins, opacities, features):
    return [p.transforms, p.means2d, p.depths, opacities, p.colors, p.normals, features, bins.q_cut]


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
    unused = wp.empty(1, dtype=float, device=dev)  # the expected depth: this op divides in torch
    outputs = [out.color, out.transmittance, out.alpha, out.depth, unused, out.inv_depth, out.normal, out.median,
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
    tail = ([fwd.transmittance, fwd.last, fwd.median_index, fwd.dist_stats, wp.empty(1, dtype=float, device=dev)]
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


class _RasterizeSurfelsFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, settings, wanted, means, quats, scales, opacities, coeffs, features, viewmat, intrinsics):
        needs = ctx.needs_input_grad[2:]
        any_grad = any(needs)
        grads, (w_means, w_quats, w_scales, w_opac, w_coeffs, w_feat, w_view, w_intr) = warp_inputs(
            (means, quats, scales, opacities, coeffs, features, viewmat, intrinsics), needs, any_grad, wp.vec2)

        tape = wp.Tape()
        with tape:
            proj = project_surfels(w_means, w_quats, w_scales, w_coeffs, w_view, w_intr, settings,
                                   requires_grad=any_grad)
        bins = bin_surfels(proj, w_opac, settings)
        fwd = blend_forward(proj, bins, w_opac, w_feat, settings, wanted)

        H, W = settings.height, settings.width
        empty = means.new_zeros(0)
        images = [wp.to_torch(getattr(fwd, name)).view(H, W, c) if image_wanted(wanted, name) else empty
                  for name, c, _ in IMAGES]
        feats = wp.to_torch(fwd.features).view(H, W, -1) if wanted.num_features else empty
        visible = wp.to_torch(bins.counts) > 0
        count = torch.tensor(bins.num_intersections)
        ctx.mark_non_differentiable(visible, count)
        ctx.state = (tape, proj, bins, fwd, w_opac, w_feat, settings, wanted, grads)
        ctx.device = means.device
        return tuple(images) + (feats, visible, count)

    @staticmethod
    def backward(ctx, *upstream):
        tape, proj, bins, fwd, w_opac, w_feat, settings, wanted, grads = ctx.state
        npix = settings.width * settings.height
        device = ctx.device
        with on_torch_stream(device):
            g = {}
            for (name, c, dtype), up in zip(IMAGES, upstream):
                if not image_wanted(wanted, name):  # outputs that were not computed: a dummy the kernel never reads
                    g[name] = wp.zeros(1, dtype=dtype)
                    continue
                t = torch.zeros((npix, c), device=device) if up is None else up.contiguous().view(npix, c)
                g[name] = wp.from_torch(t.contiguous() if c == 3 else t.view(npix), dtype=dtype)
            nf = wanted.num_features
            up_f = upstream[len(IMAGES)]
            if nf:
                t = torch.zeros((npix, nf), device=device) if up_f is None else up_f.contiguous().view(npix, nf)
                g["features"] = wp.from_torch(t)
            else:
                g["features"] = wp.zeros((1, 1), dtype=wp.float32)

            def blend_adjoint():
                blend_backward(proj, bins, w_opac, w_feat, settings, wanted, fwd, g)

            tape.record_func(blend_adjoint, [proj.transforms, proj.means2d, proj.depths, proj.colors, proj.normals,
                                             w_opac, w_feat])
            tape.backward()
        ctx.state = None
        return (None, None) + tuple(grads)


def rasterize_surfels_legacy(means, quats, scales, opacities, colors, viewmat, K, width, height, *, sh_degree=None,
                             features=None, background=None, outputs=("rgb", "alpha"), tile_size=None) -> RenderOutput:
    """`rasterize_surfels` (default thresholds, inputs unchecked) through the per-call op."""
    kw = dict(sh_degree=sh_degree, features=features, background=background, outputs=outputs)
    grad = torch.is_grad_enabled() and any(t is not None and t.requires_grad
                                           for t in (means, quats, scales, opacities, colors, features))
    tile_size = choose_tile_size(tile_size, grad, on_gpu=means.device.type == "cuda", surfels=True)
    if viewmat.dim() == 3:
        return _stack([rasterize_surfels_legacy(means, quats, scales, opacities, colors, viewmat[b], K[b], width,
                                                height, tile_size=tile_size, **kw)
                       for b in range(viewmat.shape[0])])
    coeffs, feats = op_inputs(means, colors, features, outputs)
    settings = raster_settings(width, height, 0.01, 1e10, tile_size, 0.0, sh_degree, DEFAULT_ALPHA_MIN,
                               DEFAULT_TRANSMITTANCE_MIN, DEFAULT_ALPHA_MAX)
    wanted = SurfelWanted(color="rgb" in outputs, depth="depth" in outputs, inv_depth="inv_depth" in outputs,
                          normal="normal" in outputs, median="median_depth" in outputs,
                          distortion="distortion" in outputs, num_features=feats.shape[1],
                          distortion_scale=DISTORTION_SCALE)
    with on_torch_stream(means.device):
        color, alpha, zacc, inv, normal, median, distortion, fout, visible, count = \
            _RasterizeSurfelsFunction.apply(settings, wanted, means, quats, scales, opacities, coeffs, feats,
                                            viewmat, _intrinsics_vector(K))
    out = RenderOutput(alpha=alpha if "alpha" in outputs else None, visible=visible, num_intersections=int(count))
    set_image_outputs(out, wanted, color, alpha, zacc, inv, fout, background)
    out.normal = normal if wanted.normal else None
    out.median_depth = median if wanted.median else None
    out.distortion = distortion if wanted.distortion else None
    return out
