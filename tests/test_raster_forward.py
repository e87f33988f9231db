"""Forward values of the Warp 3D rasterizer against the float64 brute-force reference."""
import pytest
import torch

from random_scenes import random_scene
from raster_helpers import render_ours, render_ref, requested
from warpgs.render.defaults import DENSE_PRIMITIVES_PER_PIXEL, choose_tile_size

TOL = 1e-4


def max_err(ours, ref, name):
    return (getattr(ours, name).double() - ref[name]).abs().max().item()


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("sh_degree", [None, 0, 1, 2, 3])
def test_forward_matches_reference(seed, sh_degree):
    scene = random_scene(n=48, seed=seed, sh_degree=sh_degree, num_features=3)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    ours = render_ours(scene, requested(scene), background=bg)
    ref = render_ref(scene, background=bg)
    assert ref["alpha"].max() > 0.5, "scene should cover the image substantially"
    for name in ("rgb", "alpha", "inv_depth", "features"):
        assert max_err(ours, ref, name) <= TOL, name
    # Depth is Σwz/alpha in scene units (z up to ~6 here): compare relative to the depth scale.
    assert max_err(ours, ref, "depth") <= TOL * ref["depth"].abs().max().item()


def test_result_does_not_depend_on_tile_size():
    scene = random_scene(n=48, seed=4)
    outs = [render_ours(scene, ("rgb", "alpha"), tile_size=t) for t in (8, 16, 32)]
    for o in outs[1:]:
        assert torch.allclose(o.rgb, outs[0].rgb, atol=1e-6)
        assert torch.allclose(o.alpha, outs[0].alpha, atol=1e-6)


def test_only_requested_outputs_are_returned():
    scene = random_scene(n=16, seed=5, num_features=2)
    out = render_ours(scene, ("alpha",))
    assert out.alpha is not None
    assert out.rgb is None and out.depth is None and out.inv_depth is None and out.features is None


def test_culled_gaussians_are_not_visible():
    scene = random_scene(n=48, seed=0)
    out = render_ours(scene, ("alpha",))
    assert not out.visible[0]  # behind the camera
    assert not out.visible[1]  # far off-screen
    assert out.visible[3:6].all()  # the stack in the middle of the view


def test_batch_of_cameras_equals_single_renders():
    scene = random_scene(n=32, seed=6)
    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    from random_scenes import look_at
    from warpgs import rasterize

    views = torch.stack([s["viewmat"], look_at((1.0, 0.0, -4.0), (0.0, 0.0, 0.0)).float()])
    Ks = torch.stack([s["K"], s["K"]])
    batch = rasterize(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], views, Ks, s["width"],
                      s["height"], outputs=("rgb", "depth"))
    assert batch.rgb.shape == (2, s["height"], s["width"], 3)
    for b in range(2):
        single = rasterize(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], views[b], Ks[b],
                           s["width"], s["height"], outputs=("rgb", "depth"))
        assert torch.equal(batch.rgb[b], single.rgb)
        assert torch.equal(batch.depth[b], single.depth)


@pytest.mark.parametrize("n", [48, 400])  # 0.04 and 0.33 Gaussians a pixel: sparse and dense
def test_default_tile_size_follows_device_and_whether_a_backward_pass_comes(n):
    """tile_size=None: 16 for forward-only GPU renders of dense scenes, else 8 (the CPU, sparse scenes, and renders
    that will be differentiated); the image is the same."""
    import torch as th

    from raster_helpers import DEVICE

    scene = random_scene(n=n, seed=4)
    explicit = {t: render_ours(scene, ("rgb",), tile_size=t) for t in (8, 16)}
    assert explicit[8].num_intersections != explicit[16].num_intersections  # tile pairs tell the sizes apart
    with th.no_grad():
        forward_only = render_ours(scene, ("rgb",))
    dense = scene["means"].shape[0] / (scene["width"] * scene["height"]) >= DENSE_PRIMITIVES_PER_PIXEL
    expected = 16 if DEVICE.startswith("cuda") and dense else 8
    assert forward_only.num_intersections == explicit[expected].num_intersections
    learnt = dict(scene, opacities=scene["opacities"].clone().requires_grad_(True))
    trained = render_ours(learnt, ("rgb",))
    assert trained.num_intersections == explicit[8].num_intersections
    assert torch.allclose(trained.rgb.detach(), forward_only.rgb, atol=1e-6)


def test_tile_size_rule():
    """The rule itself, for every device and density: a given size wins; GPU forwards of dense 3D Gaussians (or of
    3D Gaussians of unknown density) take 16; everything else, surfels included, 8."""
    assert choose_tile_size(32, needs_grad=False, on_gpu=True, primitives_per_pixel=1.0) == 32
    assert choose_tile_size(None, needs_grad=False, on_gpu=False, primitives_per_pixel=1.0) == 8
    assert choose_tile_size(None, needs_grad=True, on_gpu=True, primitives_per_pixel=1.0) == 8
    assert choose_tile_size(None, needs_grad=False, on_gpu=True, primitives_per_pixel=1.0) == 16
    assert choose_tile_size(None, needs_grad=False, on_gpu=True, primitives_per_pixel=100_000 / (1920 * 1080)) == 8
    assert choose_tile_size(None, needs_grad=False, on_gpu=True, primitives_per_pixel=300_000 / (1920 * 1080)) == 16
    assert choose_tile_size(None, needs_grad=False, on_gpu=True) == 16
    assert choose_tile_size(None, needs_grad=False, on_gpu=True, primitives_per_pixel=1.0, surfels=True) == 8
