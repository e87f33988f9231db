"""Gradients of every input, through every surfel output, against autograd on the float64 reference."""
import pytest
import torch

from warpgs.model.primitive_math import rgb_to_sh0

from reference_surfels import ALL_OUTPUTS, CHANNELS, random_surfel_scene, render_surfels_ours, render_surfels_ref

INPUTS = ("means", "quats", "scales", "opacities", "colors", "features", "viewmat", "K")


def gradients(render, scene, weights, background, dtype):
    leaves = {k: scene[k].detach().to(dtype).requires_grad_(True) for k in INPUTS if scene.get(k) is not None}
    bg = background.detach().to(dtype).requires_grad_(True)
    out = render(dict(scene, **leaves), bg)
    get = (lambda n: out[n]) if isinstance(out, dict) else (lambda n: getattr(out, n))
    loss = sum((get(n).double() * w).sum() for n, w in weights.items())
    loss.backward()
    # An input that no requested output depends on gets no gradient: compare it as zeros.
    grads = {k: (v.grad if v.grad is not None else torch.zeros_like(v)).double() for k, v in leaves.items()}
    grads["background"] = (bg.grad if bg.grad is not None else torch.zeros_like(bg)).double()
    return grads


def compare(ours, ref):
    scale = max(g.norm().item() for g in ref.values())
    for name, g_ref in ref.items():
        g = ours[name]
        assert torch.isfinite(g).all(), name
        a, b = g.flatten(), g_ref.flatten()
        if b.norm() <= 1e-9 * scale:
            # Analytically zero (e.g. the hit depth does not depend on the scales): float32 noise only.
            assert a.norm() <= 1e-5 * scale, name
            continue
        cosine = torch.nn.functional.cosine_similarity(a, b, dim=0).item()
        rel = ((a - b).norm() / b.norm()).item()
        assert cosine >= 0.999 and rel <= 1e-3, f"{name}: cosine {cosine:.6f}, relative L2 {rel:.2e}"


def weights_for(scene, outputs, seed):
    g = torch.Generator().manual_seed(seed)
    H, W = scene["height"], scene["width"]
    channels = dict(CHANNELS, features=scene["features"].shape[1] if scene["features"] is not None else 0)
    w = {n: torch.randn(H, W, channels[n], generator=g, dtype=torch.float64) for n in outputs}
    if "distortion" in w:
        w["distortion"] *= 1e3  # the term is ~1e-4: weight it as a training loss would
    return w


def check(scene, outputs, seed):
    weights = weights_for(scene, outputs, seed)
    bg = torch.tensor([0.1, 0.6, 0.3], dtype=torch.float64)
    ours = gradients(lambda s, b: render_surfels_ours(s, tuple(weights), background=b), scene, weights, bg,
                     torch.float32)
    ref = gradients(lambda s, b: render_surfels_ref(s, background=b), scene, weights, bg, torch.float64)
    if "rgb" not in outputs:  # the op adds no background without rgb
        ref["background"] = ours["background"] = torch.zeros(3, dtype=torch.float64)
    compare(ours, ref)


@pytest.mark.parametrize("sh_degree", [None, 1, 3])
@pytest.mark.parametrize("seed", [0, 1])
def test_gradients_of_all_inputs_through_all_outputs(seed, sh_degree):
    scene = random_surfel_scene(n=40, seed=seed, sh_degree=sh_degree, num_features=3)
    # Perturb the pose so viewmat's gradient is not at a symmetric point.
    scene["viewmat"][:3, 3] += torch.tensor([0.05, -0.03, 0.1], dtype=torch.float64)
    check(scene, ALL_OUTPUTS, 100 + seed)


@pytest.mark.parametrize("output", ALL_OUTPUTS)
def test_gradients_through_each_output_alone(output):
    scene = random_surfel_scene(n=40, seed=3, num_features=2)
    scene["opacities"][8:14] = 1.0  # the 0.99 alpha clamp is reached near these centres
    check(scene, (output,), 7)


def test_gradients_where_the_screen_space_fallback_dominates():
    scene = random_surfel_scene(n=40, seed=4, num_features=2)
    scene["scales"] *= 0.1  # disks under a pixel: the 1/sqrt(2) px screen-space Gaussian wins
    check(scene, ALL_OUTPUTS, 8)


def test_no_gradient_buffers_for_inputs_that_do_not_require_grad():
    from warpgs import rasterize_surfels

    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in random_surfel_scene(n=16, seed=2).items()}
    means = s["means"].clone().requires_grad_(True)
    out = rasterize_surfels(means, s["quats"], s["scales"], s["opacities"], s["colors"], s["viewmat"], s["K"],
                            s["width"], s["height"], outputs=("rgb", "normal"))
    (out.rgb.sum() + out.normal.sum()).backward()
    assert means.grad is not None and torch.isfinite(means.grad).all() and means.grad.abs().sum() > 0
    assert s["scales"].grad is None


def test_black_surfel_colours_get_gradients():
    """As tests/test_raster_gradients.py::test_colours_at_exactly_zero_get_gradients, for surfels."""
    scene = random_surfel_scene(n=40, seed=5, sh_degree=1)
    black = torch.arange(0, 40, 2)
    scene["colors"][black] = 0.0
    scene["colors"][black, 0] = float(rgb_to_sh0(torch.zeros(1))[0])  # a black initial point
    check(scene, ("rgb",), 12)


@pytest.mark.parametrize("alpha_max", [0.99, 0.999])
def test_alpha_clamp_is_a_setting_for_surfels_too(alpha_max):
    # A few large near-opaque surfels: many pixels' alpha sits between 3DGS's clamp (0.99) and gsplat's (0.999).
    scene = random_surfel_scene(n=12, seed=6, sh_degree=1)
    scene["scales"] = scene["scales"] * 5.0
    scene["opacities"] = 0.993 + 0.0069 * torch.rand(12, generator=torch.Generator().manual_seed(6),
                                                     dtype=torch.float64)
    outputs = ("rgb", "alpha", "depth", "normal")
    ours = render_surfels_ours(scene, outputs, alpha_max=alpha_max)
    ref = render_surfels_ref(scene, alpha_max=alpha_max)
    for name in outputs:
        assert torch.allclose(getattr(ours, name).double(), ref[name], atol=5e-5), name
    assert (render_surfels_ref(scene, alpha_max=1.989 - alpha_max)["alpha"] - ref["alpha"]).abs().max() > 1e-3
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    weights = weights_for(scene, outputs, 7)
    compare(gradients(lambda s, b: render_surfels_ours(s, outputs, background=b, alpha_max=alpha_max), scene,
                      weights, bg, torch.float32),
            gradients(lambda s, b: render_surfels_ref(s, background=b, alpha_max=alpha_max), scene, weights, bg,
                      torch.float64))


@pytest.mark.parametrize("screen_sigma", [0.2, 1.5])
def test_the_screen_space_fallback_width_is_a_setting(screen_sigma):
    # Sub-pixel disks, where the fallback decides what is drawn: images and gradients follow the reference at another
    # width, and the width changes the image (the setting is not ignored).
    scene = random_surfel_scene(n=40, seed=4, num_features=2)
    scene["scales"] *= 0.1
    outputs = ("rgb", "alpha", "depth", "normal", "median_depth")
    ours = render_surfels_ours(scene, outputs, screen_sigma=screen_sigma)
    ref = render_surfels_ref(scene, screen_sigma=screen_sigma)
    for name in outputs:
        assert torch.allclose(getattr(ours, name).double(), ref[name], atol=5e-5), name
    assert (render_surfels_ref(scene)["alpha"] - ref["alpha"]).abs().max() > 1e-2
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    weights = weights_for(scene, outputs, 9)
    compare(gradients(lambda s, b: render_surfels_ours(s, outputs, background=b, screen_sigma=screen_sigma), scene,
                      weights, bg, torch.float32),
            gradients(lambda s, b: render_surfels_ref(s, background=b, screen_sigma=screen_sigma), scene, weights,
                      bg, torch.float64))
    with pytest.raises(ValueError, match="screen_sigma: expected a positive number of pixels"):
        render_surfels_ours(scene, outputs, screen_sigma=0.0)
