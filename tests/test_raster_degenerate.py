"""Degenerate but finite inputs: outputs and gradients stay finite, and agree with the reference where defined."""
import torch

from random_scenes import random_scene
from raster_helpers import ALL_OUTPUTS, render_ours, render_ref

OUTPUTS = ("rgb", "alpha", "depth", "inv_depth")


def check_finite_with_grads(scene, compare_reference=True):
    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    leaves = {k: s[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")}
    from warpgs import rasterize

    out = rasterize(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"],
                    s["viewmat"], s["K"], s["width"], s["height"], outputs=OUTPUTS,
                    background=torch.tensor([0.3, 0.3, 0.3]))
    loss = sum(getattr(out, n).sum() for n in OUTPUTS)
    loss.backward()
    for n in OUTPUTS:
        assert torch.isfinite(getattr(out, n)).all(), n
    assert ((out.alpha >= 0) & (out.alpha <= 1)).all()
    for k, v in leaves.items():
        assert v.grad is None or torch.isfinite(v.grad).all(), k
    if compare_reference:
        ref = render_ref(scene, background=torch.tensor([0.3, 0.3, 0.3], dtype=torch.float64))
        for n in ("rgb", "alpha", "inv_depth"):
            assert (getattr(out, n).double() - ref[n]).abs().max() <= 1e-4, n
    return out


def test_zero_scales():
    scene = random_scene(n=24, seed=0)
    scene["scales"][:12] = 0.0
    check_finite_with_grads(scene)


def test_huge_scales():
    scene = random_scene(n=24, seed=1)
    scene["scales"][:3] = 1e6
    scene["scales"][3:6] = 1e12  # beyond the 1e8 clamp: renders like 1e8 (the reference clamps the same way)
    check_finite_with_grads(scene)


def test_zero_quaternion_is_identity_rotation():
    scene = random_scene(n=24, seed=2)
    scene["quats"][:8] = 0.0
    check_finite_with_grads(scene)
    same = dict(scene, quats=scene["quats"].clone())
    same["quats"][:8] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    a, b = render_ours(scene, ("rgb",)), render_ours(same, ("rgb",))
    assert torch.allclose(a.rgb, b.rgb, atol=1e-6)


def test_opacity_zero_and_one():
    scene = random_scene(n=24, seed=3)
    scene["opacities"][:8] = 0.0
    scene["opacities"][8:16] = 1.0
    check_finite_with_grads(scene)


def test_centres_on_and_around_the_near_plane():
    scene = random_scene(n=24, seed=4)
    near = 0.01
    # camera at z=-4 looking along +z (look_at): world z = -4 + near puts a centre exactly on the near plane
    R, t = scene["viewmat"][:3, :3], scene["viewmat"][:3, 3]
    for i, cz in enumerate([near, near * 0.999, near * 1.001, 0.0, -1e-3]):
        scene["means"][i] = R.T @ (torch.tensor([0.0, 0.0, cz], dtype=torch.float64) - t)
    out = check_finite_with_grads(scene, compare_reference=False)
    assert out.visible[0]  # z == near is kept
    assert not out.visible[3] and not out.visible[4]


def test_gaussian_at_the_camera_centre_with_sh():
    scene = random_scene(n=8, seed=5, sh_degree=3)
    R, t = scene["viewmat"][:3, :3], scene["viewmat"][:3, 3]
    scene["means"][0] = -R.T @ t  # direction to camera is undefined
    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    sh = s["colors"].clone().requires_grad_(True)
    means = s["means"].clone().requires_grad_(True)
    from warpgs import rasterize

    out = rasterize(means, s["quats"], s["scales"], s["opacities"], sh, s["viewmat"], s["K"], s["width"],
                    s["height"], sh_degree=3)
    out.rgb.sum().backward()
    assert torch.isfinite(out.rgb).all() and torch.isfinite(sh.grad).all() and torch.isfinite(means.grad).all()


def test_empty_scene():
    scene = random_scene(n=0, seed=0)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    out = render_ours(scene, ("rgb", "alpha", "depth", "inv_depth"), background=bg)
    assert torch.allclose(out.rgb, bg.float().expand_as(out.rgb))
    assert (out.alpha == 0).all() and (out.depth == 0).all() and (out.inv_depth == 0).all()
    assert out.num_intersections == 0


def test_everything_behind_the_camera():
    scene = random_scene(n=16, seed=6)
    scene["means"][:, 2] = -10.0
    out = check_finite_with_grads(scene)
    assert (out.alpha == 0).all()


def test_thousands_of_gaussians_on_one_pixel_stop_early():
    n = 3000
    scene = random_scene(n=n, seed=7)
    scene["means"] = torch.zeros(n, 3, dtype=torch.float64) + torch.linspace(0, 1, n, dtype=torch.float64)[:, None] * torch.tensor([0, 0, 1.0], dtype=torch.float64)
    scene["scales"] = torch.full((n, 3), 0.01, dtype=torch.float64)
    scene["opacities"] = torch.full((n,), 0.9, dtype=torch.float64)
    out = render_ours(scene, ALL_OUTPUTS[:4])
    assert torch.isfinite(out.rgb).all() and out.alpha.max() <= 1.0
    assert out.alpha.max() >= 1 - 1e-3  # fully opaque where they pile up, within the 1e-4 stop rule


def test_empty_scene_backward():
    """Regression (found by tests/stress): backward through a render of N=0 Gaussians used to fail."""
    from warpgs import rasterize

    leaves = [torch.zeros(0, 3, requires_grad=True), torch.zeros(0, 4, requires_grad=True),
              torch.zeros(0, 3, requires_grad=True), torch.zeros(0, requires_grad=True),
              torch.zeros(0, 3, requires_grad=True)]
    K = torch.tensor([[10.0, 0, 4], [0, 10.0, 4], [0, 0, 1]])
    out = rasterize(*leaves, torch.eye(4), K, 8, 8, outputs=("rgb", "alpha", "depth"), track_means2d=True,
                    background=torch.ones(3))
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
    assert all(t.grad is not None and t.grad.shape == t.shape for t in leaves)
    assert out.means2d.grad.shape == (0, 2)
