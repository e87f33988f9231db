"""Primitive dropout in training renders (train.drop_rate, train/dropout.py)."""
import math

import pytest
import torch
from test_sparse_train import run

from warpgs.config import ConfigError
from warpgs.train.dropout import dropped_opacities


def test_a_share_is_dropped_and_the_rest_compensated():
    torch.manual_seed(0)
    opacities = torch.rand(200_000, 1, requires_grad=True)
    out = dropped_opacities(opacities, 0.2)
    dropped = out.detach()[:, 0] == 0
    assert abs(dropped.double().mean().item() - 0.2) < 0.005
    kept = ~dropped
    torch.testing.assert_close(out.detach()[kept], opacities.detach()[kept] / 0.8)
    out.sum().backward()  # the kept rows' gradient is the compensation, the dropped rows' zero
    assert torch.allclose(opacities.grad[kept], torch.full_like(opacities.grad[kept], 1.25))
    assert not opacities.grad[dropped].any()
    assert dropped_opacities(opacities, 0.0) is opacities


def test_training_renders_drop_and_other_renders_do_not(tmp_path):
    trainer = run(tmp_path, "train.drop_rate=0.5", "strategy.refine_start=1000", steps=4)
    view = trainer.view(trainer.train_indices[0])
    whole = [trainer.render(view, ("rgb",)).rgb for _ in range(2)]
    assert torch.equal(whole[0], whole[1])  # evaluation and outputs render every primitive
    dropped = trainer.render(view, ("rgb",), drop_rate=0.5).rgb
    assert not torch.equal(dropped, whole[0])
    for _ in range(3):
        assert math.isfinite(trainer.train_step()["loss"])


def test_the_config_refuses_a_rate_outside_zero_to_one(tmp_path):
    with pytest.raises(ConfigError, match="train.drop_rate"):
        run(tmp_path, "train.drop_rate=1.0")
