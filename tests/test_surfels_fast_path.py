"""The lean surfel host path (render/fast_pipeline_surfels.py: workspace, recorded launches, no wp.Tape) renders and
differentiates every surfel output as the per-call op of tests/legacy_raster_surfels.py (the oracle) does, and
reusing scratch memory across calls (surfel and 3D renders sharing one workspace) never corrupts a render whose
backward is still pending."""
import os

import pytest
import torch

from legacy_raster_surfels import rasterize_surfels_legacy
from random_scenes import random_scene
from raster_helpers import DEVICE, assert_same_result
from reference_surfels import ALL_OUTPUTS, CHANNELS, random_surfel_scene
from warpgs import rasterize, rasterize_surfels

INPUTS = ("means", "quats", "scales", "opacities", "colors", "features", "viewmat", "K")
CAMERA_ROWS = DEVICE != "cpu" or os.environ.get("WARPGS_CPU_COOPERATIVE") == "1"  # render/camera_rows.py in use


def _leaves(scene, requires_grad=True):
    return {k: (scene[k].detach().float().to(DEVICE).requires_grad_(requires_grad)
                if scene.get(k) is not None else None) for k in INPUTS}


def _render(scene, leaves, outputs, op=rasterize_surfels, **kw):
    return op(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"],
              leaves["viewmat"], leaves["K"], scene["width"], scene["height"], sh_degree=scene["sh_degree"],
              features=leaves["features"], outputs=outputs, **kw)


def _weights(scene, outputs, seed=0):
    g = torch.Generator().manual_seed(seed)
    channels = dict(CHANNELS, features=0 if scene["features"] is None else scene["features"].shape[1])
    return {o: torch.randn(scene["height"], scene["width"], channels[o], generator=g).to(DEVICE) for o in outputs}


def _loss(out, weights):
    return sum((getattr(out, name) * w).sum() for name, w in weights.items())


def _run(scene, outputs, loss_outputs=None, op=rasterize_surfels, **kw):
    leaves = _leaves(scene)
    out = _render(scene, leaves, outputs, op=op, **kw)
    _loss(out, _weights(scene, loss_outputs or outputs)).backward()
    return out, {k: v.grad for k, v in leaves.items() if v is not None and v.grad is not None}


def _assert_same_run(run, ref, outputs):
    (out, grads), (ref_out, ref_grads) = run, ref
    for name in outputs + ("visible",):
        assert_same_result(getattr(out, name), getattr(ref_out, name), name)
    assert out.num_intersections == ref_out.num_intersections
    assert grads.keys() == ref_grads.keys()
    for name, g in ref_grads.items():  # the camera's: summed from per-surfel rows where the oracle adds atomically
        assert_same_result(grads[name], g, f"grad {name}", not (CAMERA_ROWS and name in ("viewmat", "K")))


@pytest.mark.parametrize("sh_degree,num_features,tile", [(None, 0, 8), (2, 3, 8), (None, 2, 16), (1, 0, 4)])
def test_fast_path_matches_legacy_path(sh_degree, num_features, tile):
    scene = random_surfel_scene(n=48, seed=3, sh_degree=sh_degree, num_features=num_features)
    outputs = tuple(o for o in ALL_OUTPUTS if o != "features" or num_features)
    ref = _run(scene, outputs, op=rasterize_surfels_legacy, tile_size=tile)
    _assert_same_run(_run(scene, outputs, tile_size=tile), ref, outputs)


def test_surfels_that_reach_no_pixel_skip_the_projection_adjoint_and_get_zero_gradients():
    """The surfel projection's adjoint runs only where the blend sent a gradient back: with a third of the surfels
    moved out of view every gradient still equals the oracle's full adjoint, and theirs are zero."""
    scene = random_surfel_scene(n=48, seed=3, sh_degree=2, num_features=0)
    gone = torch.arange(0, 48, 3)
    scene["means"] = scene["means"].clone()
    scene["means"][gone] += torch.tensor([60.0, 0.0, 0.0], dtype=scene["means"].dtype)
    outputs = tuple(o for o in ALL_OUTPUTS if o != "features")
    run = _run(scene, outputs)
    _assert_same_run(run, _run(scene, outputs, op=rasterize_surfels_legacy), outputs)
    grads = run[1]
    assert torch.all(grads["means"][gone] == 0) and torch.all(grads["colors"][gone] == 0)
    assert grads["means"].abs().sum() > 0


@pytest.mark.parametrize("outputs,loss_outputs", [
    (("alpha",), None),
    (("depth", "normal"), None),
    (("rgb", "median_depth"), ("median_depth",)),  # rgb unused by the loss: its upstream gradient is zeros
    (("distortion", "inv_depth", "alpha"), ("distortion",)),
])
def test_some_outputs_and_unused_ones(outputs, loss_outputs):
    scene = random_surfel_scene(n=40, seed=7)
    ref = _run(scene, outputs, loss_outputs, op=rasterize_surfels_legacy)
    _assert_same_run(_run(scene, outputs, loss_outputs), ref, outputs)


def test_forward_only_render_matches():
    scene = random_surfel_scene(n=40, seed=5, num_features=2)
    outputs = ALL_OUTPUTS
    with torch.no_grad():
        ref = _render(scene, _leaves(scene, False), outputs, op=rasterize_surfels_legacy)
        out = _render(scene, _leaves(scene, False), outputs)
    for name in outputs:
        assert_same_result(getattr(out, name), getattr(ref, name), name)


def test_interleaved_surfel_and_gaussian_renders_keep_their_own_buffers():
    """Two surfel forwards and a 3D forward on the same workspace, a forward-only render and larger renders in
    between (which reuse and grow the scratch memory), then the backwards in another order: every gradient equals
    that of a render differentiated on its own."""
    scenes = [random_surfel_scene(n=40, seed=s, num_features=2) for s in (11, 12)]
    outputs = ("rgb", "alpha", "depth", "normal", "distortion", "features")
    alone = [_run(s, outputs)[1] for s in scenes]
    gaussians = random_scene(n=50, seed=4, num_features=2)
    g_outputs = ("rgb", "alpha", "depth", "features")
    g_alone = _run(gaussians, g_outputs, op=rasterize)[1]

    leaves = [_leaves(s) for s in scenes]
    outs = [_render(s, lv, outputs) for s, lv in zip(scenes, leaves)]
    g_leaves = _leaves(gaussians)
    g_out = _render(gaussians, g_leaves, g_outputs, op=rasterize)
    with torch.no_grad():
        big = random_surfel_scene(n=120, seed=13, width=64, height=48)
        _render(big, _leaves(big, False), ("rgb", "alpha", "median_depth"))
    _run(random_surfel_scene(n=200, seed=14, width=72, height=40), ("rgb", "distortion"))
    _loss(outs[1], _weights(scenes[1], outputs)).backward()
    _loss(g_out, _weights(gaussians, g_outputs)).backward()
    _loss(outs[0], _weights(scenes[0], outputs)).backward()
    for i in (0, 1):
        for name, g in alone[i].items():
            assert_same_result(leaves[i][name].grad, g, f"scene {i} grad {name}")
    for name, g in g_alone.items():
        assert_same_result(g_leaves[name].grad, g, f"3D grad {name}")


def test_growing_and_shrinking_scenes_between_calls():
    for n, (w, h) in [(30, (40, 30)), (120, (64, 48)), (10, (16, 16)), (80, (40, 30))]:
        scene = random_surfel_scene(n=n, seed=n, width=w, height=h)
        outputs = ("rgb", "alpha", "depth")
        _assert_same_run(_run(scene, outputs), _run(scene, outputs, op=rasterize_surfels_legacy), outputs)


def test_fully_culled_scene_gives_zero_images_and_gradients():
    scene = random_surfel_scene(n=12, seed=1)
    scene["means"] = scene["means"].clone()
    scene["means"][:, 2] = -10.0  # all behind the camera: no tile pairs
    out, grads = _run(scene, ("rgb", "alpha", "normal"))
    assert out.num_intersections == 0
    assert torch.all(out.alpha == 0) and torch.all(out.normal == 0)
    for name, g in grads.items():
        assert torch.all(g == 0), name


def test_expanded_upstream_gradients():
    """`out.rgb.sum()` hands the backward a broadcast (stride-0) gradient that is copied to a contiguous one; the
    copy must stay alive while the adjoint reads it (the image is large enough that a freed copy is returned to
    the system)."""
    scene = random_surfel_scene(n=150, seed=21, width=400, height=300, num_features=2)
    outputs = ("rgb", "alpha", "normal", "features")
    results = []
    for op in (rasterize_surfels_legacy, rasterize_surfels):
        leaves = _leaves(scene)
        out = _render(scene, leaves, outputs, op=op)
        (out.rgb.sum() + out.normal[..., 2].sum() + out.features[..., 1].sum()).backward()  # alpha unused
        results.append({k: v.grad for k, v in leaves.items() if v is not None})
    for name, g in results[0].items():
        assert_same_result(results[1][name], g, f"grad {name}", not (CAMERA_ROWS and name in ("viewmat", "K")))
