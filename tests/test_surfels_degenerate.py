"""Degenerate but finite surfel inputs: outputs and gradients stay finite, and agree with the reference where
the problem is well posed."""
import torch

from reference_surfels import (ALL_OUTPUTS, quat_from_normal, random_surfel_scene, render_surfels_ours,
                               render_surfels_ref)
from warpgs import rasterize_surfels

OUTPUTS = ALL_OUTPUTS[:-1]  # everything but features
LEAVES = ("means", "quats", "scales", "opacities", "colors")
BG = torch.tensor([0.3, 0.3, 0.3], dtype=torch.float64)


def check_finite_with_grads(scene, compare_reference=True):
    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    leaves = {k: s[k].clone().requires_grad_(True) for k in LEAVES}
    view = s["viewmat"].clone().requires_grad_(True)
    out = rasterize_surfels(*(leaves[k] for k in LEAVES), view, s["K"], s["width"], s["height"], outputs=OUTPUTS,
                            background=BG.float())
    sum(getattr(out, n).sum() for n in OUTPUTS).backward()
    for n in OUTPUTS:
        assert torch.isfinite(getattr(out, n)).all(), n
    assert ((out.alpha >= 0) & (out.alpha <= 1)).all()
    for k, v in list(leaves.items()) + [("viewmat", view)]:
        assert v.grad is None or torch.isfinite(v.grad).all(), k
    if compare_reference:
        ref = render_surfels_ref(scene, background=BG)
        for n in ("rgb", "alpha", "inv_depth", "normal"):
            assert (getattr(out, n).double() - ref[n]).abs().max() <= 1e-4, n
    return out


def single_surfel(normal, opacity=0.9, scales=(0.5, 0.3), width=32, height=24):
    """One surfel at the origin seen from the look_at camera of the random scenes."""
    scene = random_surfel_scene(n=1, width=width, height=height)
    scene["means"] = torch.zeros(1, 3, dtype=torch.float64)
    scene["quats"] = quat_from_normal(torch.as_tensor(normal, dtype=torch.float64))[None]
    scene["scales"] = torch.tensor([scales], dtype=torch.float64)
    scene["opacities"] = torch.tensor([opacity], dtype=torch.float64)
    scene["colors"] = torch.tensor([[0.9, 0.2, 0.1]], dtype=torch.float64)
    return scene


def camera_centre(scene):
    R, t = scene["viewmat"][:3, :3], scene["viewmat"][:3, 3]
    return -R.T @ t


def test_exactly_edge_on_surfel_falls_back_to_the_screen_space_gaussian():
    scene = single_surfel(normal=(1.0, 0.0, 0.0))
    eye = camera_centre(scene)
    # Normal perpendicular to the line of sight to the centre: the disk's plane contains the camera.
    to_centre = -eye / eye.norm()
    side = torch.linalg.cross(to_centre, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    scene["quats"] = quat_from_normal(side)[None]
    out = check_finite_with_grads(scene, compare_reference=False)
    # The fallback is G = exp(-|d|^2) around the projected centre: a ~1 px blob that is never lost.
    assert out.alpha.max() > 0.3
    assert out.visible[0]


def test_edge_on_surfels_in_a_scene():
    scene = random_surfel_scene(n=24, seed=1)
    eye = camera_centre(scene)
    for i in range(8, 16):
        to_centre = scene["means"][i] - eye
        other = torch.randn(3, dtype=torch.float64, generator=torch.Generator().manual_seed(i))
        side = torch.linalg.cross(to_centre, other)
        scene["quats"][i] = quat_from_normal(side)
    check_finite_with_grads(scene, compare_reference=False)


def test_back_facing_surfel_renders_like_the_front_facing_one_with_the_normal_flipped():
    eye = camera_centre(single_surfel(normal=(0.0, 0.0, 1.0)))
    towards_camera = eye / eye.norm()
    front = single_surfel(normal=towards_camera + torch.tensor([0.2, 0.1, 0.0], dtype=torch.float64))
    back = single_surfel(normal=-(towards_camera + torch.tensor([0.2, 0.1, 0.0], dtype=torch.float64)))
    a = render_surfels_ours(front, OUTPUTS)
    b = render_surfels_ours(back, OUTPUTS)
    for n in OUTPUTS:
        assert torch.allclose(getattr(a, n), getattr(b, n), atol=1e-5), n
    # The rendered normal faces the camera: its direction has a positive component towards the camera.
    R = front["viewmat"][:3, :3].float()
    n_cam = a.normal.reshape(-1, 3) @ R.T  # camera space (z forward)
    assert (n_cam[a.alpha.reshape(-1) > 0.1, 2] < 0).all()
    check_finite_with_grads(back)


def test_zero_scales():
    scene = random_surfel_scene(n=24, seed=0)
    scene["scales"][:8] = 0.0
    scene["scales"][8:12, 1] = 0.0  # a line: the ray never meets it, only the screen-space Gaussian remains
    out = check_finite_with_grads(scene)
    assert out.visible[3:6].all()


def test_huge_scales():
    scene = random_surfel_scene(n=24, seed=2)
    scene["scales"][8:10] = 1e6
    scene["scales"][10:12] = 1e12  # beyond the 1e8 clamp: renders like 1e8 (the reference clamps the same way)
    check_finite_with_grads(scene)


def test_zero_quaternion_is_identity_rotation():
    scene = random_surfel_scene(n=24, seed=3)
    scene["quats"][:8] = 0.0
    check_finite_with_grads(scene)
    same = dict(scene, quats=scene["quats"].clone())
    same["quats"][:8] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    a, b = render_surfels_ours(scene, OUTPUTS), render_surfels_ours(same, OUTPUTS)
    for n in OUTPUTS:
        assert torch.allclose(getattr(a, n), getattr(b, n), atol=1e-6), n


def test_opacity_zero_and_one():
    scene = random_surfel_scene(n=24, seed=4)
    scene["opacities"][:8] = 0.0
    scene["opacities"][8:16] = 1.0
    check_finite_with_grads(scene)


def test_disk_reaching_behind_the_camera():
    # Centre in front, but the disk is large and tilted so it crosses the camera plane: its image is unbounded, the
    # footprint bounds the part in front of the near plane and on the screen, and only hits there count.
    scene = random_surfel_scene(n=12, seed=5)
    eye = camera_centre(scene)
    scene["means"][8] = eye + torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)
    scene["quats"][8] = quat_from_normal(torch.tensor([1.0, 0.2, 0.3], dtype=torch.float64))
    scene["scales"][8] = torch.tensor([3.0, 2.0], dtype=torch.float64)
    out = check_finite_with_grads(scene)
    assert out.visible[8]


def test_centres_on_and_around_the_near_plane():
    scene = random_surfel_scene(n=24, seed=6)
    near = 0.01
    R, t = scene["viewmat"][:3, :3], scene["viewmat"][:3, 3]
    for i, cz in enumerate([near, near * 0.999, near * 1.001, 0.0, -1e-3]):
        scene["means"][i] = R.T @ (torch.tensor([0.0, 0.0, cz], dtype=torch.float64) - t)
    out = check_finite_with_grads(scene, compare_reference=False)
    assert out.visible[0]  # z == near is kept
    assert not out.visible[3] and not out.visible[4]


def test_surfel_at_the_camera_centre_with_sh():
    scene = random_surfel_scene(n=8, seed=7, sh_degree=3)
    scene["means"][0] = camera_centre(scene)
    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    sh = s["colors"].clone().requires_grad_(True)
    means = s["means"].clone().requires_grad_(True)
    out = rasterize_surfels(means, s["quats"], s["scales"], s["opacities"], sh, s["viewmat"], s["K"], s["width"],
                            s["height"], sh_degree=3, outputs=OUTPUTS)
    sum(getattr(out, n).sum() for n in OUTPUTS).backward()
    assert torch.isfinite(sh.grad).all() and torch.isfinite(means.grad).all()


def test_empty_scene():
    scene = random_surfel_scene(n=0)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    out = render_surfels_ours(scene, OUTPUTS, background=bg)
    assert torch.allclose(out.rgb, bg.float().expand_as(out.rgb))
    for n in OUTPUTS[1:]:
        assert (getattr(out, n) == 0).all(), n
    assert out.num_intersections == 0


def test_everything_behind_the_camera():
    scene = random_surfel_scene(n=16, seed=8)
    scene["means"][:, 2] = -10.0
    out = check_finite_with_grads(scene)
    assert (out.alpha == 0).all()


def test_thousands_of_surfels_on_one_ray_stop_early():
    n = 2000
    scene = random_surfel_scene(n=n, seed=9)
    scene["means"] = torch.zeros(n, 3, dtype=torch.float64)
    scene["means"][:, 2] = torch.linspace(0, 1, n, dtype=torch.float64)
    scene["scales"] = torch.full((n, 2), 0.01, dtype=torch.float64)
    scene["opacities"] = torch.full((n,), 0.9, dtype=torch.float64)
    out = render_surfels_ours(scene, OUTPUTS)
    for name in OUTPUTS:
        assert torch.isfinite(getattr(out, name)).all(), name
    assert out.alpha.max() >= 1 - 1e-3 and out.alpha.max() <= 1.0
