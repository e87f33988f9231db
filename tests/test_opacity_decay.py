"""Decoupled opacity decay (train.opacity_decay, train/opacity_decay.py): each step multiplies every opacity by
(1 - d) outside the optimizer."""
import math

import pytest
import torch
from test_sparse_train import run

from warpgs.config import ConfigError
from warpgs.train.opacity_decay import decayed_logits


@pytest.mark.parametrize("decay", [0.0, 1e-4, 0.01, 0.5, 0.999])
def test_decayed_logits_scale_the_opacity_against_float64(decay):
    logits = torch.tensor([-100.0, -30.0, -5.0, -0.3, 0.0, 0.7, 4.0, 16.0, 30.0, 100.0])
    got = decayed_logits(logits, decay)
    assert torch.isfinite(got).all()
    if decay == 0.0:
        assert torch.equal(got, logits)
        return
    # float64 reference: 1 - α (1 - d) >= d, so its log is exact enough; float32 rounds a logit near 100 by 8e-6.
    want = torch.sigmoid(logits.double()) * (1.0 - decay)
    want_logits = torch.log(want) - torch.log1p(-want)
    torch.testing.assert_close(got.double(), want_logits, rtol=2e-7, atol=2e-6)
    assert (got <= logits).all()


def test_no_decay_is_the_identity_and_bad_fractions_are_refused():
    logits = torch.linspace(-20, 20, 41)
    torch.testing.assert_close(decayed_logits(logits, 0.0), logits, rtol=0, atol=2e-6)
    for bad in (-0.1, 1.0, 2.0):
        with pytest.raises(ValueError, match="train.opacity_decay"):
            decayed_logits(logits, bad)


def test_the_trainer_decays_opacities_after_each_step(tmp_path):
    """With the opacity learning rate at 0 only the decay moves opacities: after k steps each is (1 - d)^k of
    where it began (refinement off, so rows stay the same)."""
    common = ("optim.opacities_lr=0", "strategy.refine_start=1000", "losses.opacity=0")
    trainer = run(tmp_path / "on", *common, "train.opacity_decay=0.1", steps=4)
    start = trainer.model.opacities.detach().clone()
    for _ in range(3):
        assert math.isfinite(trainer.train_step()["loss"])
    torch.testing.assert_close(trainer.model.opacities.detach(), start * 0.9 ** 3, rtol=1e-5, atol=1e-7)


def test_the_config_refuses_a_decay_outside_zero_to_one(tmp_path):
    with pytest.raises(ConfigError, match="train.opacity_decay"):
        run(tmp_path, "train.opacity_decay=1.5")
