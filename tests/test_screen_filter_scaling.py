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
from warpgs.model.rendering import gaussian_low_pass, surfel_screen_sigma
from warpgs.render.defaults import DEFAULT_LOW_PASS, DEFAULT_SURFEL_SCREEN_SIGMA
from warpgs.train.trainer import Trainer


def half_view(view):
    """The same camera at half the resolution (focal lengths and principal point halved)."""
    half = copy.copy(view)
    half.K = view.K.clone()
    half.K[:2] /= 2
    half.width, half.height = view.width // 2, view.height // 2
    return half


def test_the_filters_follow_the_focal_length():
    assert surfel_screen_sigma(400.0, 400.0) == DEFAULT_SURFEL_SCREEN_SIGMA
    assert surfel_screen_sigma(100.0, 400.0) == pytest.approx(DEFAULT_SURFEL_SCREEN_SIGMA / 4)
    assert surfel_screen_sigma(800.0, None) == DEFAULT_SURFEL_SCREEN_SIGMA  # no training cameras known
    assert gaussian_low_pass(400.0, 400.0) == DEFAULT_LOW_PASS
    assert gaussian_low_pass(200.0, 400.0) == pytest.approx(DEFAULT_LOW_PASS / 4)  # px²: the square of the scale


@pytest.mark.parametrize("preset, op, setting, default, at_half", [
    ("surfels", "rasterize_surfels", "screen_sigma", DEFAULT_SURFEL_SCREEN_SIGMA, 0.5),
    (None, "rasterize", "low_pass", DEFAULT_LOW_PASS, 0.25),
])
def test_trainer_renders_pass_the_scaled_filter(tmp_path, monkeypatch, preset, op, setting, default, at_half):
    scene = write_synthetic_scene(tmp_path / "scene", "orbit", RigSettings(width=32, height=24, n_orbit=8),
                                  n_points=200)
    trainer = Trainer(resolve_config_source(preset) if preset else None,
                      overrides=[f"data.path={scene}", f"output.dir={tmp_path / 'run'}", "train.steps=2",
                                 "train.device=cpu", "train.progress=false", "eval.every=0", "eval.lpips=false"],
                      quiet=True)
    seen = []
    real = getattr(rendering, op)
    monkeypatch.setattr(rendering, op, lambda **kw: seen.append(kw.get(setting)) or real(**kw))
    view = trainer.scene.view(trainer.scene.train[0], trainer.device)
    trainer.render(view)
    out = trainer.render(half_view(view))
    assert out.rgb.shape[:2] == (12, 16) and torch.isfinite(out.rgb).all()
    assert seen[0] == default  # a training view: exactly 2DGS's width / 3DGS's low-pass
    assert seen[1] == pytest.approx(default * at_half)


def test_a_configured_surfel_width_is_the_training_views_and_scales_too(tmp_path, monkeypatch):
    scene = write_synthetic_scene(tmp_path / "scene", "orbit", RigSettings(width=32, height=24, n_orbit=8),
                                  n_points=200)
    trainer = Trainer(resolve_config_source("surfels"),
                      overrides=[f"data.path={scene}", f"output.dir={tmp_path / 'run'}", "train.steps=2",
                                 "train.device=cpu", "train.progress=false", "eval.every=0", "eval.lpips=false",
                                 "train.surfel_screen_sigma=0.1"], quiet=True)
    seen = []
    real = rendering.rasterize_surfels
    monkeypatch.setattr(rendering, "rasterize_surfels", lambda **kw: seen.append(kw.get("screen_sigma")) or real(**kw))
    view = trainer.scene.view(trainer.scene.train[0], trainer.device)
    trainer.render(view)
    trainer.render(half_view(view))
    assert seen == [pytest.approx(0.1), pytest.approx(0.05)]


@pytest.mark.parametrize("value", ["0", "-0.5", "inf"])
def test_a_surfel_width_that_is_not_a_positive_number_is_named(value):
    from warpgs.config.loader import load_config
    from warpgs.config.schema import ConfigError

    with pytest.raises(ConfigError, match="train.surfel_screen_sigma"):
        load_config(None, [f"train.surfel_screen_sigma={value}"])
