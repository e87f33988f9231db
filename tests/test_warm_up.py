"""The kernels are compiled before the training clock starts (train/warm_up.py): the warm-up's render, loss and
backward leave nothing behind (gradients, random numbers, view order), so a run with it trains bit for bit as the
same run without it, and its time is a set-up stage of its own."""
import json

import torch

import warpgs.train.loop as loop
from train_fixtures import quick_overrides
from warpgs.train.trainer import Trainer
from warpgs.train.warm_up import compile_step_kernels

# Dropout draws random numbers in every training render: the run sees them only if the warm-up hands them back.
RUN = {"train.drop_rate": 0.1, "extensions.environment.degree": 2}


def _final_params(tmp_path, monkeypatch, warm: bool) -> dict:
    if not warm:
        monkeypatch.setattr(loop, "compile_step_kernels", lambda trainer: None)
    trainer = Trainer(None, overrides=quick_overrides(tmp_path / ("warm" if warm else "cold"), steps=25, **RUN),
                      quiet=True)
    trainer.fit()
    monkeypatch.undo()
    stages = json.loads((trainer.out_dir / "metrics.json").read_text())["stage_seconds"]
    assert "compile_kernels" in stages  # (without the warm-up: the stage of a call that does nothing)
    return {name: p.detach().clone() for name, p in trainer.named_parameters()}


def test_run_with_warm_up_trains_as_without(tmp_path, monkeypatch):
    warm = _final_params(tmp_path, monkeypatch, warm=True)
    cold = _final_params(tmp_path, monkeypatch, warm=False)
    assert warm.keys() == cold.keys()
    for name in warm:
        assert torch.equal(warm[name], cold[name]), name


def test_warm_up_leaves_no_gradients_or_random_draws(tmp_path):
    trainer = Trainer(None, overrides=quick_overrides(tmp_path, steps=5, **RUN), quiet=True)
    params = {name: p.detach().clone() for name, p in trainer.named_parameters()}
    rng, queue = torch.get_rng_state(), list(trainer.views.queue)
    compile_step_kernels(trainer)
    assert all(p.grad is None for _, p in trainer.named_parameters())
    assert all(torch.equal(p, params[name]) for name, p in trainer.named_parameters())
    assert torch.equal(torch.get_rng_state(), rng) and trainer.views.queue == queue and trainer.step == 0
