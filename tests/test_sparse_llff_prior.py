"""The few-view depth prior (issue 15): the plane sweep's margin confidence and multi-view consistency check, the
confidence written with the prior and served with the view, and the Marr terms weighted by it."""
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from warpgs.data import Camera, PlaneSweepStereo, PointCloud, compute_depth_priors, load_scene
from warpgs.data.depth.consistency import consistent_views
from warpgs.data.depth.files import read_exr_channels, write_exr
from warpgs.data.depth.plane_sweep import LEGACY_SETTINGS
from warpgs.data.formats.llff import POSES_FILE, save_poses_bounds
from warpgs.losses import marr

W, H, F, Z0 = 96, 72, 80.0, 5.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])


def _camera(x: float, name: str = "") -> Camera:
    view = np.eye(4)
    view[0, 3] = -x  # centre at (x, 0, 0), looking down +z
    return Camera(K, view, W, H, name=name)


def _plane_coords(x: float):
    v, u = np.mgrid[0:H, 0:W] + 0.5
    return x + (u - W / 2) / F * Z0, (v - H / 2) / F * Z0  # world X, Y where each pixel's ray meets z = Z0


def plane_scene(root: Path, xs=(-0.3, 0.0, 0.3), unrelated: bool = False, sensor: float = 0.0):
    """Three views of a textured plane at depth Z0 with a flat (textureless) square in the middle; `unrelated`:
    every view an independent noise image instead (no surface in common); `sensor`: per-view image noise."""
    rng = np.random.default_rng(0)
    freq, phase = rng.uniform(-4, 4, (24, 2)), rng.uniform(0, 2 * np.pi, 24)
    cams = []
    for i, x in enumerate(xs):
        cam = _camera(x, f"IMG_{i:03d}.png")
        X, Y = _plane_coords(x)
        img = 0.5 + 1.2 * np.mean([np.sin(2 * np.pi * (f[0] * X + f[1] * Y) + p) for f, p in zip(freq, phase)], 0)
        img = np.where((np.abs(X) < 0.5) & (np.abs(Y) < 0.5), 0.5, img)
        if unrelated:
            img = np.random.default_rng(100 + i).random((H, W))
        img = np.clip(img + sensor * np.random.default_rng(200 + i).standard_normal((H, W)), 0, 1)
        (root / "images").mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.repeat((img * 255).astype(np.uint8)[..., None], 3, -1)).save(root / "images" / cam.name)
        cams.append(cam)
    save_poses_bounds(cams, root / POSES_FILE, (3.0, 8.0))
    return load_scene(root, split="all")


def plane_scene_with_points(root: Path):
    """plane_scene with SfM points on the plane (every 37th pixel's ray of the middle view), to align priors to."""
    X, Y = _plane_coords(0.0)
    xyz = np.stack([X.ravel()[::37], Y.ravel()[::37], np.full(X.size, Z0)[::37]], 1)
    return plane_scene(root).with_points(PointCloud(xyz, np.full((len(xyz), 3), 0.5)))


# --- the consistency check ---------------------------------------------------------------------------------------
def test_depth_maps_of_one_surface_agree_and_others_do_not():
    ref, other = _camera(0.0), _camera(0.4)
    plane = torch.full((H, W), Z0, dtype=torch.float64)
    ok = torch.ones(H, W, dtype=torch.bool)
    agree, checked = consistent_views(ref, plane, [(other, plane, ok)])
    inside = checked > 0
    assert inside.float().mean() > 0.7 and bool((agree[inside] == 1).all())  # every pixel it sees agrees
    assert int(checked[:, :3].sum()) == 0  # the left edge falls outside the other view: nothing to check
    agree, checked = consistent_views(ref, plane, [(other, plane * 1.1, ok)])  # 10 % off: no agreement
    assert int(agree.sum()) == 0 and bool((checked == inside.int()).all())
    agree, checked = consistent_views(ref, plane, [(other, plane, torch.zeros_like(ok))])  # nothing valid there
    assert int(checked.sum()) == 0
    # An occluder only the other view sees (nearer, over part of its image): those pixels are checked, not agreed.
    occluded = plane.clone()
    occluded[:, W // 2:] = 2.0
    agree, checked = consistent_views(ref, plane, [(other, occluded, ok)])
    assert 0 < int(agree.sum()) < int(checked.sum())
    with pytest.raises(ValueError, match="ref_depth"):
        consistent_views(ref, plane[:-1], [(other, plane, ok)])


# --- the plane sweep -------------------------------------------------------------------------------------------------
def _regions():
    X, Y = _plane_coords(0.0)
    flat = (np.abs(X) < 0.3) & (np.abs(Y) < 0.3)  # at least 3 px inside the flat square: no texture in reach
    textured = (np.abs(X) > 0.7) | (np.abs(Y) > 0.7)
    return flat, textured


@pytest.mark.parametrize("sensor", [0.0, 0.02])
def test_the_sweep_trusts_texture_not_a_flat_patch(tmp_path, sensor):
    scene = plane_scene(tmp_path, sensor=sensor)
    est = PlaneSweepStereo(near=3.0, far=8.0).estimate(scene, [0, 1, 2])[1]
    flat, textured = _regions()
    depth = 1.0 / np.maximum(est.inv_depth, 1e-9)
    assert est.valid[textured].mean() > 0.98
    assert np.abs(depth - Z0)[textured & est.valid].mean() / Z0 < 0.01
    assert est.confidence[textured].mean() > 0.9
    # Validity is permissive (chance agreements pass the consistency check); the confidence, which weights the
    # depth losses, is what keeps the flat patch out.
    assert est.confidence[flat].mean() < 0.05
    assert est.confidence.min() >= 0 and est.confidence.max() <= 1 and (est.confidence[~est.valid] == 0).all()


def test_views_without_a_common_surface_carry_no_confidence(tmp_path):
    scene = plane_scene(tmp_path, unrelated=True)
    new = PlaneSweepStereo(near=3.0, far=8.0).estimate(scene, [0, 1, 2])[1]
    assert new.confidence.mean() < 0.05


def test_the_old_rule_trusted_weak_texture_the_new_one_does_not():
    """fern's walls and floor: the old distinctiveness (median - best) / median divides by a median that is ~0 on a
    weakly textured pixel. One pixel's cost curve over 7 planes: flat at noise level with a slightly lower dip."""
    weak = torch.tensor([0.0030, 0.0031, 0.0029, 0.0010, 0.0030, 0.0032, 0.0030])[:, None, None]
    sharp = torch.tensor([0.120, 0.110, 0.090, 0.010, 0.090, 0.110, 0.120])[:, None, None]
    inv = torch.linspace(0.1, 0.4, 7, dtype=torch.float64)
    old, new = PlaneSweepStereo(**LEGACY_SETTINGS), PlaneSweepStereo()
    for volume, trusted_by_new in ((weak, False), (sharp, True)):
        o, n = old._select(volume, inv), new._select(volume, inv)
        assert o.valid.all() and o.confidence.item() > 0.6  # the old rule trusts both
        assert (n.confidence.item() > 0.9) == trusted_by_new
    assert new._select(weak, inv).confidence.item() < 0.2


def test_settings_are_checked():
    with pytest.raises(ValueError, match="confidence"):
        PlaneSweepStereo(confidence="peak")
    with pytest.raises(ValueError, match="best_fraction"):
        PlaneSweepStereo(best_fraction=0.0)


# --- written with the prior, served with the view ------------------------------------------------------------------
def test_priors_keep_their_confidence_and_views_serve_it(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    scene = plane_scene_with_points(tmp_path / "scene")
    estimator = PlaneSweepStereo(near=3.0, far=8.0)
    with_priors, report = compute_depth_priors(scene, estimator, out_dir=tmp_path / "priors")
    assert all(v["confidence"] for v in report["views"].values())
    channels = read_exr_channels(tmp_path / "priors" / "IMG_001.exr")
    assert set(channels) >= {"Z", "valid", "confidence"}
    view = with_priors.view(1)
    conf = view.inv_depth_confidence
    assert conf.shape == (H, W, 1) and float(conf.min()) >= 0 and float(conf.max()) <= 1
    assert bool((conf[~view.inv_depth_valid] == 0).all())
    want = estimator.estimate(scene, [1], sources=[0, 1, 2])[1].confidence
    np.testing.assert_allclose(conf[..., 0].numpy(), np.where(view.inv_depth_valid[..., 0].numpy(), want, 0),
                               atol=1e-6)
    assert with_priors.downscaled(2).view(1).inv_depth_confidence.shape == (H // 2, W // 2, 1)
    # A prior without the channel (another tool's file) serves none, and the losses fall back to plain means.
    write_exr(tmp_path / "other" / "IMG_001.exr", np.full((H, W), 1 / Z0, np.float32), "inverse_depth")
    other = scene.with_depth_priors(tmp_path / "other")
    for _ in range(2):  # the second read comes from the scene's memory
        view = other.view(1)
        assert view.inv_depth_prior is not None and view.inv_depth_confidence is None


# --- the losses ----------------------------------------------------------------------------------------------------
def _maps(values):
    return torch.tensor(values, dtype=torch.float32).reshape(1, 1, *np.shape(values))


def test_depth_terms_are_confidence_weighted_means():
    pred, prior = _maps([[1.0, 2.0], [3.0, 4.0]]), torch.zeros(1, 1, 2, 2)
    mask = torch.ones(1, 1, 2, 2, dtype=torch.bool)
    weight = _maps([[1.0, 0.0], [0.5, 0.5]])
    assert marr.depth_l1(pred, prior, mask).item() == pytest.approx(2.5)
    assert marr.depth_l1(pred, prior, mask, weight).item() == pytest.approx((1 + 1.5 + 2) / 2)
    assert marr.depth_l1(pred, prior, mask, torch.zeros_like(weight)).item() == 0.0  # nothing trusted: no pull
    # The 3x3 terms weight a pixel by the least confident pixel of its window.
    assert torch.equal(marr.window_min(_maps([[1.0, 1.0, 1.0], [1.0, 0.2, 1.0], [1.0, 1.0, 1.0]])),
                       _maps([[0.0, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.0]]))


def _render_out(inv):
    class Out:
        pass

    out = Out()
    out.inv_depth = inv
    out.alpha = torch.ones_like(inv)
    return out


def test_the_depth_loss_reads_confidence_from_the_batch_or_its_view():
    rng = torch.Generator().manual_seed(0)
    inv = torch.rand(8, 8, 1, generator=rng).requires_grad_(True)
    prior = torch.rand(8, 8, 1, generator=rng) + 0.5
    conf = torch.zeros(8, 8, 1)
    conf[:4] = 1.0  # only the top half is trusted
    base = {"inv_depth_prior": prior, "inv_depth_valid": torch.ones(8, 8, 1, dtype=torch.bool)}

    class View:
        inv_depth_confidence = conf

    for batch in ({**base, "inv_depth_confidence": conf}, {**base, "view": View()}):
        inv.grad = None
        loss = marr.depth(_render_out(inv), batch, None, 0)
        loss.backward()
        assert loss.item() == pytest.approx((inv[:4] - prior[:4]).abs().mean().item(), rel=1e-5)
        assert float(inv.grad[4:].abs().max()) == 0.0 and float(inv.grad[:4].abs().min()) > 0
    try:
        marr.configure(confidence_power=0.0)  # ignore the confidence: the plain mean of every valid pixel
        plain = marr.depth(_render_out(inv), {**base, "inv_depth_confidence": conf}, None, 0)
        assert plain.item() == pytest.approx((inv - prior).abs().mean().item(), rel=1e-5)
    finally:
        marr.configure(confidence_power=1.0)
    with pytest.raises(ValueError, match="inv_depth_confidence"):
        marr.depth(_render_out(inv), {**base, "inv_depth_confidence": conf[:4]}, None, 0)
    with pytest.raises(ValueError, match="inv_depth_confidence.*NaN"):
        marr.depth(_render_out(inv), {**base, "inv_depth_confidence": conf * float("nan")}, None, 0)
    # A map found finite is not checked again (a host read every step on a GPU), unless it changes in place.
    marr.depth(_render_out(inv), {**base, "inv_depth_confidence": conf}, None, 0)
    conf[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="inv_depth_confidence.*NaN"):
        marr.depth(_render_out(inv), {**base, "inv_depth_confidence": conf}, None, 0)
    # A map made under inference_mode has no version counter to remember it by: checked each time, no error.
    with torch.inference_mode():
        made = torch.ones(8, 8, 1)
        marr.depth(_render_out(inv.detach()), {**base, "inv_depth_confidence": made}, None, 0)
    assert torch.isfinite(marr.depth(_render_out(inv), {**base, "inv_depth_confidence": made}, None, 0))


# --- initial points from the prior (model.prior_points) ----------------------------------------------------------
def test_prior_points_lie_on_the_surface_and_only_where_confident(tmp_path, monkeypatch):
    from warpgs.config import load_config
    from warpgs.train.setup import initial_points, prior_points

    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    scene = plane_scene_with_points(tmp_path / "scene")
    with_priors, _ = compute_depth_priors(scene, PlaneSweepStereo(near=3.0, far=8.0), out_dir=tmp_path / "priors")
    xyz, rgb, note = prior_points(with_priors, 600, 0.5)
    assert len(xyz) == 600 and rgb.shape == (600, 3) and "confidence >= 0.5" in note
    assert float((xyz[:, 2] - Z0).abs().median()) < 0.02 * Z0  # on the plane the views see
    # Only pixels at least that confident: the flat square in the middle has no texture to match, so no point.
    central = (xyz[:, 0].abs() < 0.4) & (xyz[:, 1].abs() < 0.4)
    anywhere, _, _ = prior_points(with_priors, 600, 0.0)
    assert int(central.sum()) < int(((anywhere[:, 0].abs() < 0.4) & (anywhere[:, 1].abs() < 0.4)).sum())
    # Added to model.init's points; a scene without priors is refused by the key's name.
    cfg = load_config(None, ["model.init=sfm", "model.prior_points=300", "train.device=cpu"])
    got, _, source = initial_points(with_priors, cfg)
    assert len(got) == len(scene.points) + 300 and "300 from depth priors" in source
    with pytest.raises(ValueError, match="model.prior_points=300"):
        initial_points(scene, cfg)


def test_auto_prior_confidence_follows_the_training_view_count(tmp_path, monkeypatch):
    from warpgs.config import ConfigError, load_config
    from warpgs.train.lifted_prior import AUTO_FEW, AUTO_FEW_MAX_VIEWS, AUTO_MANY, confidence_for
    from warpgs.train.setup import initial_points

    assert AUTO_FEW > AUTO_MANY
    views = (3, AUTO_FEW_MAX_VIEWS, AUTO_FEW_MAX_VIEWS + 1, 24)
    assert [confidence_for("auto", n) for n in views] == [AUTO_FEW, AUTO_FEW, AUTO_MANY, AUTO_MANY]
    assert confidence_for(0.3, 24) == 0.3 and confidence_for("0.7", 3) == 0.7
    assert load_config(None, ["model.prior_points_confidence=auto"]).model.prior_points_confidence == "auto"
    for bad in ("high", "1.5", "-0.1"):
        with pytest.raises(ConfigError, match="model.prior_points_confidence"):
            load_config(None, [f"model.prior_points_confidence={bad}"])
    # The start line names the threshold "auto" chose for this scene's training views.
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    scene = plane_scene_with_points(tmp_path / "scene")
    with_priors, _ = compute_depth_priors(scene, PlaneSweepStereo(near=3.0, far=8.0), out_dir=tmp_path / "priors")
    cfg = load_config(None, ["model.init=sfm", "model.prior_points=300", "model.prior_points_confidence=auto",
                             "train.device=cpu"])
    _, _, source = initial_points(with_priors, cfg)
    assert f"confidence >= {confidence_for('auto', len(with_priors.train)):g}" in source
