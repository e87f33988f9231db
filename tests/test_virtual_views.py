"""Virtual views (train.virtual_views, train/virtual_views.py): cameras between two training cameras, the lifted
prior's nearest point per pixel as their target, and the trainer's extra pass."""
import math

import numpy as np
import pytest
import torch
from test_sparse_train import run

from warpgs.train.virtual_views import (VirtualViews, between, neighbour_pairs, rotation_exp, rotation_log,
                                        splat_points, virtual_loss)

W, H, F = 32, 24, 30.0
K = torch.tensor([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])


def _viewmat(angle: float, axis, centre) -> np.ndarray:
    rot = rotation_exp(angle * np.asarray(axis, np.float64) / np.linalg.norm(axis))
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = -rot @ np.asarray(centre, np.float64)
    return out


def test_a_virtual_camera_lies_between_its_two_cameras():
    a = _viewmat(0.1, [0, 1, 0], [-1.0, 0.0, 0.0])
    b = _viewmat(-0.5, [1, 1, 0], [1.0, 0.4, 0.2])
    np.testing.assert_allclose(between(a, b, 0.0), a, atol=1e-12)
    np.testing.assert_allclose(between(a, b, 1.0), b, atol=1e-12)
    mid = between(a, b, 0.5)
    centre = -mid[:3, :3].T @ mid[:3, 3]
    np.testing.assert_allclose(centre, [0.0, 0.2, 0.1], atol=1e-12)
    # Halfway along the rotation: the same angle from each end, half the whole.
    whole = np.linalg.norm(rotation_log(a[:3, :3].T @ b[:3, :3]))
    to_a = np.linalg.norm(rotation_log(a[:3, :3].T @ mid[:3, :3]))
    to_b = np.linalg.norm(rotation_log(mid[:3, :3].T @ b[:3, :3]))
    assert whole > 0.3 and to_a == pytest.approx(whole / 2, abs=1e-9) and to_b == pytest.approx(whole / 2, abs=1e-9)
    assert np.allclose(mid[:3, :3] @ mid[:3, :3].T, np.eye(3), atol=1e-12)


def _plane_points(depth: float, colour):
    """One point per pixel of the identity camera, on the plane z = depth, at the pixel centres."""
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    z = torch.full_like(u, depth)
    xyz = torch.stack([(u - W / 2) / F * z, (v - H / 2) / F * z, z], -1).reshape(-1, 3)
    return xyz, torch.tensor(colour, dtype=torch.float32).expand(len(xyz), 3).clone()


def test_points_seen_from_their_own_camera_give_back_their_depth_and_colour():
    xyz, rgb = _plane_points(4.0, [0.2, 0.5, 0.9])
    image, inv, mask = splat_points(xyz, rgb, torch.eye(4), K, W, H)
    assert bool(mask.all())
    torch.testing.assert_close(inv, torch.full((H, W, 1), 0.25))
    torch.testing.assert_close(image, rgb.view(H, W, 3))


def test_the_nearest_point_wins_and_a_far_point_seen_through_a_gap_is_dropped():
    far, far_rgb = _plane_points(8.0, [1.0, 0.0, 0.0])
    near, near_rgb = _plane_points(4.0, [0.0, 1.0, 0.0])
    hole = torch.ones(H, W, dtype=torch.bool)
    hole[10, 12] = False  # the near surface misses one pixel
    image, inv, mask = splat_points(torch.cat([far, near[hole.view(-1)]]),
                                    torch.cat([far_rgb, near_rgb[hole.view(-1)]]), torch.eye(4), K, W, H)
    assert float(inv[0, 0]) == pytest.approx(0.25) and image[0, 0].tolist() == [0.0, 1.0, 0.0]
    assert not bool(mask[10, 12]) and int(mask.sum()) == H * W - 1
    # Behind the camera or off the image: no target.
    behind = torch.tensor([[0.0, 0.0, -1.0], [100.0, 0.0, 1.0]])
    _, _, none = splat_points(behind, torch.ones(2, 3), torch.eye(4), K, W, H)
    assert not bool(none.any())


def test_draws_repeat_by_step_and_need_two_cameras():
    xyz, rgb = _plane_points(4.0, [0.5, 0.5, 0.5])
    cams = [(_viewmat(0.0, [0, 1, 0], [x, 0.0, 0.0]), K.numpy(), W, H) for x in (-0.2, 0.0, 0.2)]
    sampler = VirtualViews(cams, xyz, rgb, seed=3)
    one, again, other = sampler.draw(7), sampler.draw(7), sampler.draw(8)
    assert torch.equal(one.viewmat, again.viewmat) and not torch.equal(one.viewmat, other.viewmat)
    centre = -(one.viewmat[:3, :3].T @ one.viewmat[:3, 3])
    assert -0.2 <= float(centre[0]) <= 0.2 and abs(float(centre[1])) < 1e-6
    assert bool(one.mask.any()) and one.image.shape == (H, W, 3)
    with pytest.raises(ValueError, match="train.virtual_views: needs at least 2"):
        VirtualViews(cams[:1], xyz, rgb)


def _ring(n: int, radius: float = 2.0):
    """n cameras on a circle in the x-z plane, each looking at its centre (a 360° capture)."""
    out = []
    for i in range(n):
        angle = 2 * math.pi * i / n
        rot = rotation_exp(np.array([0.0, math.pi + angle, 0.0]))  # +z (the view direction) turned towards the centre
        centre = radius * np.array([math.sin(angle), 0.0, math.cos(angle)])
        vm = np.eye(4)
        vm[:3, :3], vm[:3, 3] = rot.T, -rot.T @ centre
        out.append(vm)
    return out


def test_virtual_cameras_around_a_360_capture_stay_between_adjacent_cameras():
    ring = _ring(8)
    # Each camera looks at the centre: the origin lies on its optical axis, in front of it.
    assert all(vm[2, 3] > 0 and np.allclose(vm[:2, 3], 0.0, atol=1e-9) for vm in ring)
    pairs = neighbour_pairs(ring)
    assert sorted(pairs) == sorted([(a, (a + d) % 8) for a in range(8) for d in (1, 7)])
    assert sorted(neighbour_pairs(ring[:3])) == [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)]  # three: any two
    xyz, rgb = _plane_points(4.0, [0.5, 0.5, 0.5])
    sampler = VirtualViews([(vm, K.numpy(), W, H) for vm in ring], xyz, rgb, seed=1)
    chord = 2 * 2.0 * math.sin(math.pi / 8)
    for step in range(40):  # never through the middle of the ring, where a random pair's chord would pass
        vm = sampler.draw(step).viewmat.double().numpy()
        centre = -vm[:3, :3].T @ vm[:3, 3]
        assert np.linalg.norm(centre) >= math.sqrt(4.0 - chord ** 2 / 4) - 1e-6


class _Out:
    def __init__(self, rgb, inv):
        self.rgb, self.inv_depth = rgb, inv


def test_the_loss_is_an_l1_over_the_pixels_with_a_target():
    xyz, rgb = _plane_points(4.0, [0.2, 0.5, 0.9])
    cams = [(np.eye(4), K.numpy(), W, H), (_viewmat(0.0, [0, 1, 0], [0.01, 0, 0]), K.numpy(), W, H)]
    view = VirtualViews(cams, xyz, rgb).draw(0)
    m = view.mask.float()
    rendered = (view.image + 0.1).requires_grad_(True)
    inv = (view.inv_depth - 0.05).requires_grad_(True)
    loss = virtual_loss(_Out(rendered, inv), view, 2.0, 3.0)
    assert float(loss.detach()) == pytest.approx(2.0 * 0.1 + 3.0 * 0.05, rel=1e-4)
    loss.backward()
    assert bool((rendered.grad[~view.mask.expand(H, W, 3)] == 0).all()) and float(rendered.grad.abs().sum()) > 0
    torch.testing.assert_close(inv.grad, -3.0 * m / m.sum())


def test_the_trainer_adds_a_virtual_pass_that_moves_the_model(tmp_path):
    base = run(tmp_path / "off", steps=4)
    trainer = run(tmp_path / "on", "train.virtual_views=1", "train.virtual_rgb=1", "train.virtual_depth=1", steps=4)
    assert base.virtual_views is None and trainer.virtual_views is not None
    assert len(trainer.virtual_views.points) > 100
    # The same first step but for the virtual view's gradient.
    before = trainer.model.means.detach().clone()
    assert torch.equal(before, base.model.means.detach())
    for t in (base, trainer):
        info = t.train_step()
        assert math.isfinite(info["loss"])
    assert not torch.equal(trainer.model.means.detach(), base.model.means.detach())
    for _ in range(3):
        assert math.isfinite(trainer.train_step()["loss"])


def test_virtual_views_need_depth_priors_and_valid_weights(tmp_path):
    with pytest.raises(ValueError, match="data.depth_priors: 'none', but train.virtual_views read depth priors"):
        run(tmp_path / "a", "train.virtual_views=1", "data.depth_priors=null", "losses.depth=0",
            "losses.depth_grad=0", "losses.depth_local=0")
    with pytest.raises(ValueError, match="train.virtual_depth"):
        run(tmp_path / "b", "train.virtual_views=1", "train.virtual_depth=-1")
    with pytest.raises(ValueError, match="train.virtual_views"):
        run(tmp_path / "c", "train.virtual_views=-2")


def test_auto_turns_virtual_views_on_with_few_training_views_only(tmp_path):
    from warpgs.train.virtual_views import AUTO_MAX_VIEWS, virtual_every

    assert [virtual_every("auto", n) for n in (2, 3, AUTO_MAX_VIEWS, AUTO_MAX_VIEWS + 1, 9, 24)] == [1, 1, 1, 0, 0, 0]
    assert virtual_every(0, 3) == 0 and virtual_every(4, 30) == 4
    # The tiny light field trains on its 3x3 array: 9 views, so "auto" leaves them off; with 3 of them, on.
    nine = run(tmp_path / "nine", "train.virtual_views=auto", steps=2)
    assert nine.virtual_every == 0 and nine.virtual_views is None
    dropped = [nine.scene.names[v] for v in nine.scene.train[3:]]
    three = run(tmp_path / "three", "train.virtual_views=auto", f"data.exclude=[{', '.join(dropped)}]", steps=2)
    assert len(three.views.indices) == 3 and three.virtual_every == 1 and three.virtual_views is not None
    assert math.isfinite(three.train_step()["loss"])
    for bad in ("sometimes", -1):
        with pytest.raises(ValueError, match="train.virtual_views"):
            run(tmp_path / "bad", f"train.virtual_views={bad}")


def test_the_start_line_says_whether_auto_turned_virtual_views_on():
    from warpgs.train.virtual_views import AUTO_MAX_VIEWS, virtual_views_note

    off = virtual_views_note("auto", 0, AUTO_MAX_VIEWS + 1)
    assert "off" in off and f"{AUTO_MAX_VIEWS + 1} training views" in off and f"at most {AUTO_MAX_VIEWS}" in off
    assert virtual_views_note("auto", 1, 3) == virtual_views_note(1, 1, 3) == "; virtual views every 1 step(s)"
    assert virtual_views_note(0, 0, 3) == ""  # not asked for: nothing to explain
