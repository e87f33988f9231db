"""Renders of a trained model scale the screen-space filter with the image (model/rendering.py): surfels their
fallback width (2DGS's 1/sqrt(2) px at the training resolution, half of it at half the resolution), 3D Gaussians
their low-pass (0.3 px², a quarter of it at half the resolution), so a primitive seen smaller than in training is not
dilated to a fixed pixel size (benchmarks/zoom_out.py measures what that does)."""
import copy

import pytest
import torch

import warpgs.model.rendering as rendering
from warpgs.cli.commands import resolve_config_source
from warpgs.data.formats.synthetic import RigSettings, write_synthetic_scene
from warpgs.model.rendering import surfel_screen_sigma
from warpgs.render.defaults import DEFAULT_SURFEL_SCREEN_SIGMA
from warpgs.train.trainer import Trainer


def test_the_width_follows_the_focal_length():
    assert surfel_screen_sigma(400.0, 400.0) == DEFAULT_SURFEL_SCREEN_SIGMA
    assert surfel_screen_sigma(100.0, 400.0) == pytest.approx(DEFAULT_SURFEL_SCREEN_SIGMA / 4)
    assert surfel_screen_sigma(800.0, None) == DEFAULT_SURFEL_SCREEN_SIGMA  # no training cameras known


def test_trainer_renders_pass_the_scaled_width(tmp_path, monkeypatch):
    scene = write_synthetic_scene(tmp_path / "scene", "orbit", RigSettings(width=32, height=24, n_orbit=8),
                                  n_points=200)
    trainer = Trainer(resolve_config_source("surfels"), overrides=[f"data.path={scene}", f"output.dir={tmp_path / 'run'}", "train.steps=2",
                                            "train.device=cpu", "train.progress=false", "eval.every=0",
                                            "eval.lpips=false"], quiet=True)
    seen = []
    real = rendering.rasterize_surfels
    monkeypatch.setattr(rendering, "rasterize_surfels", lambda **kw: seen.append(kw.get("screen_sigma")) or real(**kw))
    view = trainer.scene.view(trainer.scene.train[0], trainer.device)
    trainer.render(view)
    half = copy.copy(view)
    half.K = view.K.clone()
    half.K[:2] /= 2
    half.width, half.height = view.width // 2, view.height // 2
    out = trainer.render(half)
    assert out.rgb.shape[:2] == (12, 16) and torch.isfinite(out.rgb).all()
    assert seen[0] == DEFAULT_SURFEL_SCREEN_SIGMA  # a training view: exactly 2DGS's width
    assert seen[1] == pytest.approx(DEFAULT_SURFEL_SCREEN_SIGMA / 2)


def test_gaussian_renders_scale_the_low_pass(tmp_path, monkeypatch):
    from warpgs.model.rendering import gaussian_low_pass
    from warpgs.render.defaults import DEFAULT_LOW_PASS

    assert gaussian_low_pass(400.0, 400.0) == DEFAULT_LOW_PASS
    assert gaussian_low_pass(200.0, 400.0) == pytest.approx(DEFAULT_LOW_PASS / 4)  # px²: the square of the scale
    scene = write_synthetic_scene(tmp_path / "scene", "orbit", RigSettings(width=32, height=24, n_orbit=8),
                                  n_points=200)
    trainer = Trainer(None, overrides=[f"data.path={scene}", f"output.dir={tmp_path / 'run'}", "train.steps=2",
                                       "train.device=cpu", "train.progress=false", "eval.every=0",
                                       "eval.lpips=false"], quiet=True)
    seen = []
    real = rendering.rasterize
    monkeypatch.setattr(rendering, "rasterize", lambda **kw: seen.append(kw.get("low_pass")) or real(**kw))
    view = trainer.scene.view(trainer.scene.train[0], trainer.device)
    trainer.render(view)
    half = copy.copy(view)
    half.K = view.K.clone()
    half.K[:2] /= 2
    half.width, half.height = view.width // 2, view.height // 2
    trainer.render(half)
    assert seen[0] == DEFAULT_LOW_PASS and seen[1] == pytest.approx(DEFAULT_LOW_PASS / 4)
