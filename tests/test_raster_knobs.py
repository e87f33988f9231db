"""The accuracy knobs alpha_min and transmittance_min: the renderers follow the float64 references at any
setting (forward and gradients), raising them really drops work and changes the image, and bad values are
refused by name."""
import pytest
import torch

from random_scenes import random_scene
from raster_helpers import render_ours, render_ref, requested
from reference_surfels import random_surfel_scene, render_surfels_ours, render_surfels_ref
from test_raster_gradients import compare, gradients
import test_surfels_gradients as surfel_grads

TOL = 1e-4
KNOBS = [dict(alpha_min=0.05, transmittance_min=1e-4), dict(alpha_min=1 / 255, transmittance_min=0.2),
         dict(alpha_min=0.1, transmittance_min=0.05)]


def max_err(ours, ref, name):
    return (getattr(ours, name).double() - ref[name]).abs().max().item()


@pytest.mark.parametrize("knobs", KNOBS)
def test_gaussians_forward_follows_reference_at_other_thresholds(knobs):
    scene = random_scene(n=48, seed=5, sh_degree=1, num_features=2)
    ours = render_ours(scene, requested(scene), **knobs)
    ref = render_ref(scene, **knobs)
    default = render_ref(scene)
    # The knob must matter on this scene, or the comparison proves nothing.
    assert (ref["rgb"] - default["rgb"]).abs().max() > 1e-2
    for name in ("rgb", "alpha", "inv_depth", "features"):
        assert max_err(ours, ref, name) <= TOL, name


@pytest.mark.parametrize("knobs", KNOBS[::2])
def test_gaussians_gradients_follow_reference_at_other_thresholds(knobs):
    scene = random_scene(n=40, seed=6, sh_degree=1, num_features=2)
    g = torch.Generator().manual_seed(11)
    H, W = scene["height"], scene["width"]
    channels = {"rgb": 3, "alpha": 1, "depth": 1, "inv_depth": 1, "features": 2}
    weights = {n: torch.randn(H, W, channels[n], generator=g, dtype=torch.float64) for n in requested(scene)}
    bg = torch.tensor([0.3, 0.2, 0.7], dtype=torch.float64)
    ours = gradients(lambda s, b: render_ours(s, tuple(weights), background=b, **knobs), scene, weights, bg,
                     torch.float32)
    ref = gradients(lambda s, b: render_ref(s, background=b, **knobs), scene, weights, bg, torch.float64)
    compare(ours, ref)


@pytest.mark.parametrize("knobs", KNOBS)
def test_surfels_forward_follows_reference_at_other_thresholds(knobs):
    scene = random_surfel_scene(n=48, seed=5, num_features=2)
    outputs = ("rgb", "alpha", "depth", "normal", "median_depth", "features")
    ours = render_surfels_ours(scene, outputs, **knobs)
    ref = render_surfels_ref(scene, **knobs)
    assert (ref["rgb"] - render_surfels_ref(scene)["rgb"]).abs().max() > 1e-2
    for name in ("rgb", "alpha", "normal", "features"):
        assert max_err(ours, ref, name) <= TOL, name


@pytest.mark.parametrize("knobs", KNOBS[::2])
def test_surfels_gradients_follow_reference_at_other_thresholds(knobs):
    scene = random_surfel_scene(n=40, seed=6, num_features=2)
    outputs = ("rgb", "alpha", "depth", "normal", "features")
    weights = surfel_grads.weights_for(scene, outputs, seed=12)
    bg = torch.tensor([0.3, 0.2, 0.7], dtype=torch.float64)
    ours = surfel_grads.gradients(lambda s, b: render_surfels_ours(s, outputs, background=b, **knobs), scene,
                                  weights, bg, torch.float32)
    ref = surfel_grads.gradients(lambda s, b: render_surfels_ref(s, background=b, **knobs), scene, weights, bg,
                                 torch.float64)
    surfel_grads.compare(ours, ref)


def test_a_higher_alpha_threshold_drops_tile_work():
    scene = random_scene(n=48, seed=7)
    base = render_ours(scene, ("rgb",))
    cut = render_ours(scene, ("rgb",), alpha_min=0.2)
    assert cut.num_intersections < base.num_intersections


@pytest.mark.parametrize("name,value", [("alpha_min", 0.0), ("alpha_min", 0.995), ("transmittance_min", 1.0),
                                        ("transmittance_min", -0.1), ("transmittance_min", 0.0),
                                        ("max_sigmas", -1.0)])
def test_bad_knob_values_are_refused_by_name(name, value):
    scene = random_scene(n=8, seed=0)
    with pytest.raises(ValueError, match=name):
        render_ours(scene, ("rgb",), **{name: value})
    surfels = random_surfel_scene(n=8, seed=0)
    with pytest.raises(ValueError, match=name):
        render_surfels_ours(surfels, ("rgb",), **{name: value})
