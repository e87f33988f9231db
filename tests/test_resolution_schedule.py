"""train.resolution_schedule (train/resolution.py): coarse-to-fine training views."""
import math

import imageio.v3 as imageio
import pytest
import torch

from warpgs.train.resolution import ScaledViews, downscaled_view, factor_at, parse_schedule


class FakeView:
    def __init__(self, width=8, height=6):
        self.index, self.width, self.height = 3, width, height
        self.K = torch.tensor([[10.0, 0.0, 4.0], [0.0, 12.0, 3.0], [0.0, 0.0, 1.0]])
        self.image = torch.arange(height * width * 3, dtype=torch.float32).reshape(height, width, 3)
        self.mask = torch.zeros(height, width, 1, dtype=torch.bool)
        self.mask[:, : width // 2] = True
        self.inv_depth_prior = None


def test_schedule_is_parsed_and_checked():
    assert parse_schedule(None) == [] and parse_schedule([]) == []
    assert parse_schedule([[0, 4], [100, 2], [300, 1]]) == [(0, 4), (100, 2), (300, 1)]
    for bad, match in (([[5, 2]], "start at step 0"), ([[0, 2], [0, 1]], "increase"), ([[0, 0]], ">= 1"),
                       ([[0, 1.5]], "integers"), ([3], "pairs")):
        with pytest.raises(ValueError, match="train.resolution_schedule: .*" + match):
            parse_schedule(bad)


def test_factor_in_force_at_each_step():
    schedule = parse_schedule([[0, 4], [100, 2], [300, 1]])
    assert [factor_at(schedule, s) for s in (0, 99, 100, 299, 300, 10_000)] == [4, 4, 2, 2, 1, 1]
    assert factor_at([], 5) == 1


def test_downscaled_view_averages_the_image_and_scales_the_intrinsics():
    view = FakeView()
    half = downscaled_view(view, 2)
    assert (half.width, half.height) == (4, 3) and half.image.shape == (3, 4, 3)
    want = view.image.reshape(3, 2, 4, 2, 3).mean(dim=(1, 3))  # 2x2 block means
    assert torch.allclose(half.image, want)
    assert torch.allclose(half.K[0], view.K[0] / 2) and torch.allclose(half.K[1], view.K[1] / 2)
    assert half.mask.dtype == torch.bool and half.mask.shape == (3, 4, 1)
    assert half.mask[:, :2].all() and not half.mask[:, 2:].any()
    assert view.width == 8 and view.image.shape == (6, 8, 3)  # the source is untouched
    assert downscaled_view(view, 1) is view


def test_scaled_views_follow_the_step():
    views = ScaledViews([[0, 2], [10, 1]])
    view = FakeView()
    assert views.at(view, 0).width == 4 and views.at(view, 9).width == 4
    assert views.at(view, 10) is view
    assert ScaledViews(None).at(view, 0) is view  # no schedule: every view as it is


def test_trainer_trains_coarse_then_fine_and_evaluates_at_full_resolution(tmp_path):
    from warpgs.config.loader import load_config
    from warpgs.train.trainer import Trainer

    cfg = load_config(None, ["steps=4", "train.device=cpu", "eval.every=0", "data.width=32", "data.height=24",
                             f"output.dir={tmp_path}", "train.progress=false",
                             "train.resolution_schedule=[[0, 2], [2, 1]]"])
    trainer = Trainer(cfg, quiet=True)
    index = trainer.scene.train[0]
    assert (trainer.view(index).width, trainer.view(index).height) == (16, 12)
    seen = []
    for _ in range(4):
        seen.append(trainer.view(index).width)
        trainer.train_step()
    assert seen == [16, 16, 32, 32]
    trainer.step = 0  # a coarse step: evaluation still renders the full-resolution test views
    metrics = trainer.evaluate(save_images=True)
    assert math.isfinite(metrics["psnr"])
    saved = sorted(p for p in tmp_path.rglob("*.png"))
    assert saved and all(imageio.imread(p).shape[1] in (32, 64) for p in saved)  # full width (or side by side)
