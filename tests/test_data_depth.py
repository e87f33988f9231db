"""Depth priors: file formats, robust scale/shift alignment, the built-in plane-sweep estimator, the learned
video-depth adapter's plumbing and errors, and point initialisation from depth."""
import json
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from data_fixtures import copy_of, default_lightfield, synthetic_dir
from warpgs.data import (DepthModelUnavailable, VideoDepthAnything, align_depth_to_points,
                         align_inverse_depth, compute_depth_priors, depth_metrics, initial_points, load_scene,
                         points_from_depth, random_points, read_depth, read_inverse_depth, write_exr)
from warpgs.data.formats.image_io import to_uint8
from warpgs.data.formats.lightfield import pseudo_video_order
from warpgs.data.depth.estimators import DepthEstimate, DepthEstimator
from warpgs.data.depth.video_depth import PseudoVideoDepth


def test_depth_file_formats(tmp_path):
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 20.0, (12, 16)).astype(np.float32)
    depth[0, 0] = 0.0  # no measurement
    depth[1, 1] = np.inf  # sky
    write_exr(tmp_path / "d.exr", depth, "depth")
    inv, valid = read_inverse_depth(tmp_path / "d.exr")  # the EXR says what it holds
    assert not valid[0, 0] and valid[1, 1] and inv[1, 1] == 0.0
    np.testing.assert_allclose(inv[valid & np.isfinite(depth)], 1 / depth[valid & np.isfinite(depth)], rtol=1e-6)
    np.save(tmp_path / "inv.npy", np.where(np.isfinite(depth) & (depth > 0), 1 / np.maximum(depth, 1e-9), 0)[..., None])
    inv2, valid2 = read_inverse_depth(tmp_path / "inv.npy", kind="inverse_depth")
    np.testing.assert_allclose(inv2[valid2], inv[valid & (inv > 0)], rtol=1e-6)
    mm = np.round(np.where(np.isfinite(depth), depth, 0) * 1000).astype(np.uint16)
    mm[mm > 60000] = 0
    Image.fromarray(mm).save(tmp_path / "d.png")
    d3, valid3 = read_depth(tmp_path / "d.png", kind="depth", scale=0.001)
    np.testing.assert_allclose(d3[valid3], mm[valid3] / 1000.0, rtol=1e-6)
    with pytest.raises(ValueError, match="d.png"):
        read_depth(tmp_path / "d.png")  # a PNG cannot say whether it holds depth or inverse depth


def test_alignment_recovers_known_scale_and_shift_with_outliers():
    rng = np.random.default_rng(1)
    target = 1.0 / rng.uniform(1.0, 10.0, 400)  # inverse depth of SfM points
    scale, shift = 2.7, -0.035
    prior = (target - shift) / scale + rng.normal(0, 0.0003, target.shape)  # ~0.1-1% of the signal
    bad = rng.choice(len(target), 100, replace=False)  # 25% gross outliers: wrong matches
    prior[bad] = rng.uniform(prior.min(), prior.max(), len(bad))
    fit = align_inverse_depth(prior, target)
    assert fit.scale == pytest.approx(scale, rel=0.01)
    assert abs(fit.shift - shift) < 0.01 * abs(shift)
    assert 280 <= fit.n_inliers <= 320 and fit.n_points == 400
    assert fit.rms < 0.002 and fit.median_relative < 0.01
    plain = np.linalg.lstsq(np.stack([prior, np.ones_like(prior)], 1), target, rcond=None)[0]
    assert abs(plain[0] - scale) > 0.1 * scale  # ordinary least squares is pulled away by the outliers
    print(f"alignment: scale {fit.scale:.4f} (true {scale}), shift {fit.shift:.5f} (true {shift}), "
          f"rms {fit.rms:.2e}, inliers {fit.n_inliers}/{fit.n_points}")


def test_alignment_to_the_synthetic_sfm_points():
    scene = load_scene(synthetic_dir("lightfield"))
    v = scene.train[4]
    depth, valid = scene.depth_np(v)
    inv = np.where(valid, 1.0 / depth, 0.0)
    prior = (inv - 0.02) / 3.0  # what an affine-invariant model might output
    seen = scene.visible_points(v)
    fit = align_depth_to_points(prior, valid & np.isfinite(depth), scene.cameras[v], scene.points.xyz[seen])
    assert fit.scale == pytest.approx(3.0, rel=0.01) and fit.shift == pytest.approx(0.02, rel=0.01)
    assert fit.n_points > 400 and fit.median_relative < 0.01


def test_plane_sweep_priors_on_the_light_field():
    """The default scene's priors: plane-sweep stereo from the other 8 grid views, aligned to the SfM points."""
    path, seconds, _ = default_lightfield()
    scene = load_scene(path)
    report = json.loads((path / "depth_priors" / "format.json").read_text())
    assert report["estimator"] == "plane_sweep" and report["kind"] == "inverse_depth"
    rows = []
    for v in scene.train:
        gt, gt_valid = scene.depth_np(v)
        prior, valid = scene.inv_depth_prior_np(v)
        assert prior.shape == (96, 128)
        has_gt = gt_valid & np.isfinite(gt)
        pred = 1.0 / np.maximum(prior, 1e-9)
        m = depth_metrics(pred, gt, valid & has_gt)
        rows.append((m["abs_rel"], m["delta_1_25"], (valid & has_gt).sum() / has_gt.sum()))
        # Stereo is metric already, so its alignment to the SfM points is close to the identity.
        fit = report["views"][scene.names[v]]["alignment"]
        assert fit["scale"] == pytest.approx(1.0, abs=0.05) and abs(fit["shift"]) < 0.01
    absrel, delta, coverage = np.mean(rows, axis=0)
    print(f"plane-sweep priors, 3x3 light field, 128x96: AbsRel {absrel:.4f}, delta<1.25 {delta:.4f} over the valid "
          f"pixels, which cover {coverage:.1%} of the pixels with depth; scene + priors generated in {seconds:.1f} s")
    # Invalid pixels are stored as 0 and masked; benchmarks/depth_prior.py also scores the raw estimate everywhere.
    assert absrel < 0.03 and delta > 0.98 and coverage > 0.9


def test_a_view_without_sfm_points_gets_no_prior_instead_of_failing(monkeypatch, capsys):
    """3 views around a 360° capture can leave one view with no triangulated point to bound its sweep: that view
    gets an empty (all-invalid) prior and a note naming it; the others are swept as before. With no view bounded
    the sweep fails, naming one."""
    from warpgs.data import PlaneSweepStereo

    path, _, _ = default_lightfield()
    scene = load_scene(path)
    views = list(scene.train[:3])
    blind = views[1]
    seen = scene.visible_points
    monkeypatch.setattr(scene, "visible_points", lambda v: seen(v)[:0] if v == blind else seen(v))
    estimates = PlaneSweepStereo(num_sources=2).estimate(scene, views)
    assert not estimates[blind].valid.any() and not estimates[blind].confidence.any()
    assert all(estimates[v].valid.mean() > 0.3 for v in views if v != blind)
    assert repr(scene.names[blind]) in capsys.readouterr().err
    monkeypatch.setattr(scene, "visible_points", lambda v: seen(v)[:0])
    with pytest.raises(ValueError, match=f"{scene.names[views[0]]}.*no SfM points"):
        PlaneSweepStereo(num_sources=2).estimate(scene, views)


class _CornerOnlyEstimate(DepthEstimator):
    """The scene's true inverse depth, valid everywhere except on one view, where only one pixel is: that view
    sees its SfM points but its prior meets fewer than the 3 an alignment needs (as 12 views around a 360° capture
    left one)."""

    name = "corner_only"

    def __init__(self, blind: int, metric: bool):
        self.blind, self.metric = blind, metric

    def estimate(self, scene, views, sources=None):
        out = {}
        for v in views:
            depth, valid = scene.depth_np(v)
            valid = valid & np.isfinite(depth) & (depth > 0)
            if v == self.blind:
                valid = np.zeros_like(valid)
                valid[0, 0] = True
            out[v] = DepthEstimate(np.where(valid, 1 / np.maximum(depth, 1e-9), 0).astype(np.float32), valid,
                                   self.metric)
        return out


def test_a_metric_prior_that_meets_too_few_points_is_kept_unaligned(tmp_path, capsys):
    path, _, _ = default_lightfield()
    scene = load_scene(path)
    views = list(scene.train[:3])
    blind = views[1]
    _, report = compute_depth_priors(scene, _CornerOnlyEstimate(blind, metric=True), views=views, out_dir=tmp_path / "m")
    assert report["views"][scene.names[blind]]["alignment"] is None
    assert all(report["views"][scene.names[v]]["alignment"]["scale"] == pytest.approx(1, abs=1e-3)
               for v in views if v != blind)
    assert f"{scene.names[blind]!r} kept unaligned" in capsys.readouterr().err
    with pytest.raises(ValueError, match=f"view {scene.names[blind]!r}: depth alignment needs at least 3"):
        compute_depth_priors(scene, _CornerOnlyEstimate(blind, metric=False), views=views, out_dir=tmp_path / "r")


def test_priors_are_served_with_the_scene(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path))  # downscaled images are cached there
    path, _, _ = default_lightfield()
    scene = load_scene(path)
    v = scene.view(scene.train[0])
    assert v.inv_depth_prior.shape == (96, 128, 1) and v.inv_depth_valid.dtype == torch.bool
    assert scene.view(scene.test[0]).inv_depth_prior is None
    small = scene.downscaled(2).view(scene.train[0])
    assert small.inv_depth_prior.shape == (48, 64, 1)
    full = v.inv_depth_prior[..., 0].numpy()
    ok = small.inv_depth_valid[..., 0].numpy()
    block_mean = full.reshape(48, 2, 64, 2).mean((1, 3))
    block_valid = v.inv_depth_valid[..., 0].numpy().reshape(48, 2, 64, 2).all((1, 3))
    np.testing.assert_allclose(small.inv_depth_prior[..., 0].numpy()[ok & block_valid], block_mean[ok & block_valid],
                               rtol=1e-5)


class _FrameLookupModel(PseudoVideoDepth):
    """Stands in for a learned video model: recognises each frame and returns an affine copy of its exact inverse
    depth (the kind of output a relative model gives), recording the order it saw frames in."""

    name = "frame_lookup"

    def __init__(self, scene):
        self.table = {to_uint8(scene.image_np(v)[0]).tobytes(): v for v in range(len(scene))}
        self.scene, self.seen = scene, []

    def predict_video(self, frames):
        out = []
        for f in frames:
            v = self.table[f.tobytes()]
            self.seen.append(v)
            depth, valid = self.scene.depth_np(v)
            out.append(np.where(valid, 0.5 / depth + 0.1, 0.1))  # sky -> 0.1: affine of inverse depth 0
        return np.stack(out)


def test_video_depth_adapter_plumbing_and_alignment(tmp_path):
    scene = load_scene(copy_of("lightfield", tmp_path / "lf"))
    model = _FrameLookupModel(scene)
    with_priors, report = compute_depth_priors(scene, model)
    names = [scene.names[v] for v in model.seen]
    assert names == ["r0_c0.png", "r0_c1.png", "r0_c2.png", "r1_c2.png", "r1_c1.png", "r1_c0.png",
                     "r2_c0.png", "r2_c1.png", "r2_c2.png"]  # serpentine pseudo-video
    for v in scene.train:
        fit = report["views"][scene.names[v]]["alignment"]
        assert fit["scale"] == pytest.approx(2.0, rel=0.01) and fit["shift"] == pytest.approx(-0.2, abs=0.002)
        prior, valid = with_priors.inv_depth_prior_np(v)
        gt, gt_valid = scene.depth_np(v)
        finite = gt_valid & np.isfinite(gt) & valid
        assert depth_metrics(1 / np.maximum(prior, 1e-12), gt, finite)["abs_rel"] < 1e-3


def test_video_depth_anything_reports_what_is_missing(tmp_path, monkeypatch):
    with pytest.raises(DepthModelUnavailable, match="video_depth_anything"):
        VideoDepthAnything(tmp_path / "video_depth_anything_vits.pth")
    # With the package importable but no checkpoint, the error names the checkpoint path.
    (tmp_path / "pkg" / "video_depth_anything").mkdir(parents=True)
    (tmp_path / "pkg" / "video_depth_anything" / "__init__.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path / "pkg"))
    monkeypatch.delitem(sys.modules, "video_depth_anything", raising=False)
    with pytest.raises(DepthModelUnavailable, match="missing.pth"):
        VideoDepthAnything(tmp_path / "missing.pth")


def test_pseudo_video_order_is_serpentine():
    pos = {f"{r}{c}": (float(r), float(c)) for r in range(3) for c in range(3)}
    names = sorted(pos) + ["extra"]
    order = pseudo_video_order(pos, names)
    assert [names[i] for i in order] == ["00", "01", "02", "12", "11", "10", "20", "21", "22", "extra"]


def test_point_initialisation_from_depth_and_random():
    scene = load_scene(synthetic_dir("orbit"))
    pts = points_from_depth(scene, n=2000, source="depth")
    assert len(pts) == 2000
    # Lifted points project back onto pixels whose depth they carry.
    cam = scene.cameras[scene.train[0]]
    pix, z = cam.project(pts.xyz)
    depth, _ = scene.depth_np(scene.train[0])
    inside = (pix[:, 0] >= 0) & (pix[:, 0] < 128) & (pix[:, 1] >= 0) & (pix[:, 1] < 96) & (z > 0)
    d = depth[pix[inside, 1].astype(int), pix[inside, 0].astype(int)]
    assert np.median(np.abs(d - z[inside]) / z[inside]) < 0.02
    rnd = random_points(scene, n=1000)
    assert len(rnd) == 1000 and np.isfinite(rnd.xyz).all()
    assert np.linalg.norm(rnd.xyz.mean(0) - [0, 0, 0.35]) < 1.5  # around what the cameras look at
    lf = load_scene(synthetic_dir("lightfield"))
    with pytest.raises(ValueError, match="parallel"):
        random_points(lf, n=10)  # a planar array has no focus point: near/far must be given
    assert len(random_points(lf, n=10, near=1.0, far=10.0)) == 10
    points, origin = initial_points(lf)
    assert origin == "sfm" and points is lf.points
