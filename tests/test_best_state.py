"""train.steps=auto goes back to its best validated state at the stop (train/best_state.py), and the parameter
copy it uses (optim.copy_parameters / load_parameters) restores rows and Adam state exactly."""
from __future__ import annotations

import pytest
import torch

from train_fixtures import Interrupt, quick_overrides
from warpgs.model.gaussians import GaussianModel
from warpgs.train.best_state import BestState
from warpgs.train.loop import TrainingLoop
from warpgs.train.optim import build_optimizer, copy_parameters, load_parameters, update_rows
from warpgs.train.trainer import Trainer

AUTO = {"train.steps": "auto", "schedule.max_steps": 200, "schedule.val_every": 20, "schedule.patience": 40,
        "schedule.settle": 20, "schedule.polish": 20, "train.checkpoint_every": 0,
        "strategy.refine_stop_fraction": 0.5}


def adam_step(model, optimizer, seed):
    g = torch.Generator().manual_seed(seed)
    for p in model.params.values():
        p.grad = torch.randn(p.shape, generator=g)
    optimizer.step()
    optimizer.zero_grad()


def test_loaded_parameters_and_adam_state_are_the_copied_ones():
    torch.manual_seed(0)
    model = GaussianModel.from_points(torch.randn(50, 3), torch.rand(50, 3), sh_degree=1)
    optimizer = build_optimizer(model, None, 1.0)
    adam_step(model, optimizer, 1)
    saved = copy_parameters(model, optimizer)
    expected = {n: p.detach().clone() for n, p in model.params.items()}
    update_rows(model, optimizer, keep=torch.arange(50) % 3 > 0, append={n: p[:7].detach() for n, p in model.params.items()})
    adam_step(model, optimizer, 2)
    assert model.num_primitives != 50
    load_parameters(model, optimizer, saved)
    for name, p in model.params.items():
        assert torch.equal(p.detach(), expected[name])
        state = optimizer.state[p]
        assert torch.equal(state["exp_avg"], saved[name]["state"]["exp_avg"])
        assert torch.equal(state["exp_avg_sq"], saved[name]["state"]["exp_avg_sq"])
        assert any(q is p for group in optimizer.param_groups for q in group["params"])
    # The restored model trains on as the copied one would have: the same next step from the same state.
    twin = GaussianModel.from_points(torch.randn(50, 3), torch.rand(50, 3), sh_degree=1)
    twin_opt = build_optimizer(twin, None, 1.0)
    load_parameters(twin, twin_opt, saved)
    adam_step(model, optimizer, 3)
    adam_step(twin, twin_opt, 3)
    for name in model.params:
        assert torch.equal(model.params[name].detach(), twin.params[name].detach())


def test_load_names_a_mismatch():
    model = GaussianModel.from_points(torch.randn(5, 3), torch.rand(5, 3), sh_degree=0)
    optimizer = build_optimizer(model, None, 1.0)
    saved = copy_parameters(model, optimizer)
    saved.pop("means")
    with pytest.raises(ValueError, match="saved parameters"):
        load_parameters(model, optimizer, saved)
    with pytest.raises(RuntimeError, match="nothing was captured"):
        BestState().restore(None)


def scripted_validation(peak_step=40, drop=1.0):
    """A validation curve that peaks at peak_step and then stays `drop` dB lower: the rule stops with the best
    state behind it."""
    def score(loop):
        s = loop.trainer.step
        return 20.0 + min(s, peak_step) / 10.0 - (drop if s > peak_step else 0.0)
    return score


class Record:
    """Copies of the parameters at chosen steps (taken after the step, before the rule looks at it)."""

    def __init__(self, steps):
        self.steps, self.params = set(steps), {}

    def __call__(self, trainer, step, info):
        if trainer.step in self.steps:
            self.params[trainer.step] = {n: p.detach().clone() for n, p in trainer.model.params.items()}


def test_auto_run_goes_back_to_its_best_state(tmp_path, monkeypatch):
    monkeypatch.setattr(TrainingLoop, "_validation_psnr", scripted_validation())
    restored = []
    original = BestState.restore

    def spy(self, parts):
        original(self, parts)
        restored.append({n: p.detach().clone() for n, p in parts.model.params.items()})
    monkeypatch.setattr(BestState, "restore", spy)
    record = Record([40])
    result = Trainer(None, overrides=quick_overrides(tmp_path / "full", **AUTO), quiet=True, callbacks=[record]).fit()
    stop = result.metrics["schedule"]["decisions"][-1]
    assert stop["decision"] == "stop" and stop["restored_step"] == 40 and "back to the state of step 40" in stop["reason"]
    assert len(restored) == 1 and restored[0].keys() == record.params[40].keys()
    for name, value in record.params[40].items():
        assert torch.equal(restored[0][name], value)
    assert result.steps == stop["step"] + 20  # then the polish

    # Interrupted after the best (the copy is in the checkpoint), resumed: the same end.
    out = tmp_path / "part"
    part = Trainer(None, overrides=quick_overrides(out, **AUTO), quiet=True, callbacks=[Interrupt(60)])
    with pytest.raises(KeyboardInterrupt):
        part.fit()
    resumed = Trainer(None, overrides=quick_overrides(out, **AUTO), quiet=True, resume=True)
    assert resumed.best_state.step == 40
    again = resumed.fit()
    assert again.metrics["schedule"] == result.metrics["schedule"]
    assert again.metrics["psnr"] == pytest.approx(result.metrics["psnr"], abs=1e-4)


def test_keep_best_off_and_a_latest_score_as_good_as_the_best_keep_the_model(tmp_path, monkeypatch):
    monkeypatch.setattr(TrainingLoop, "_validation_psnr", scripted_validation())
    off = Trainer(None, overrides=quick_overrides(tmp_path / "off", **AUTO, **{"schedule.keep_best": "false"}),
                  quiet=True)
    assert off.best_state is None
    assert "restored_step" not in off.fit().metrics["schedule"]["decisions"][-1]
    # A drop inside min_gain is no worse than the best: nothing to go back to.
    monkeypatch.setattr(TrainingLoop, "_validation_psnr", scripted_validation(drop=0.01))
    flat = Trainer(None, overrides=quick_overrides(tmp_path / "flat", **AUTO), quiet=True).fit()
    assert "restored_step" not in flat.metrics["schedule"]["decisions"][-1]


def test_host_copies_reuse_and_grow_their_buffers():
    from warpgs.train.host_copies import GROWTH, HostCopies
    host = HostCopies()
    a = host.copy("a", torch.arange(12.0).view(4, 3))
    assert torch.equal(a, torch.arange(12.0).view(4, 3))
    storage = a.untyped_storage().data_ptr()
    b = host.copy("a", torch.ones(3, 3))  # fewer rows (a refine pruned some): the same buffer
    assert b.untyped_storage().data_ptr() == storage and torch.equal(b, torch.ones(3, 3))
    c = host.copy("a", torch.full((8, 3), 2.0))  # more rows: a new buffer, with room to grow
    assert c.untyped_storage().data_ptr() != storage and torch.equal(c, torch.full((8, 3), 2.0))
    assert host.nbytes() == int(24 * GROWTH) * 4
    d = host.copy("b", torch.zeros(2, dtype=torch.int64))  # another key keeps its own buffer
    assert torch.equal(c, torch.full((8, 3), 2.0)) and d.dtype == torch.int64


def test_the_checkpointed_best_state_holds_only_its_rows():
    # The live copy is a view of a buffer a quarter larger; a checkpoint must not carry the spare rows.
    model = GaussianModel.from_points(torch.randn(40, 3), torch.rand(40, 3), sh_degree=1)
    optimizer = build_optimizer(model, None, 1.0)
    adam_step(model, optimizer, 1)

    class Parts:
        modules, module_optimizer = torch.nn.ModuleDict(), None
    parts = Parts()
    parts.model, parts.optimizer = model, optimizer
    best = BestState()
    best.capture(7, parts)
    saved = best.state_dict()
    assert saved["step"] == 7
    for name, p in model.params.items():
        value = saved["params"][name]["value"]
        assert torch.equal(value, p.detach())
        assert value.untyped_storage().nbytes() == value.numel() * value.element_size()
        assert torch.equal(saved["params"][name]["state"]["exp_avg"], optimizer.state[p]["exp_avg"])
