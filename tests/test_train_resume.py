"""Checkpoints: resume is bit-exact on CPU, Ctrl-C keeps (or cleanly writes) the checkpoint, the NaN guard stops
at the first non-finite value and leaves the last good checkpoint alone."""
import hashlib
import os
import signal

import pytest
import torch

from train_fixtures import quick_overrides
from warpgs.train.checkpoint import load_checkpoint
from warpgs.losses import register_loss, unregister_loss
from warpgs.train.trainer import NonFiniteError, Trainer

STEPS = 40  # densification at 20 and 30, SH degree raised at 15 and 30


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("straight")
    trainer = Trainer(None, overrides=quick_overrides(out, STEPS), quiet=True)
    result = trainer.fit()
    return result, {n: p.detach().clone() for n, p in trainer.model.params.items()}


@pytest.fixture
def default_sigint():
    """Python's own Ctrl-C handler for the test (a background job starts with SIGINT ignored), restored after."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_sigint_checkpoints_at_step_boundary_and_resume_is_exact(tmp_path, uninterrupted, default_sigint):
    reference, ref_params = uninterrupted

    def press_ctrl_c(trainer, step, info):
        if step == 16:
            os.kill(os.getpid(), signal.SIGINT)

    overrides = quick_overrides(tmp_path, STEPS)
    first = Trainer(None, overrides=overrides, callbacks=[press_ctrl_c], quiet=True)
    with pytest.raises(KeyboardInterrupt):
        first.fit()
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == 17  # the step that was running finished
    assert not list(tmp_path.glob(".*.tmp"))
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handler restored

    resumed = Trainer(None, overrides=overrides, resume=True, quiet=True)
    assert resumed.step == 17
    result = resumed.fit()
    assert result.steps == reference.steps == STEPS
    assert result.loss == reference.loss  # bit-exact on CPU
    assert result.num_primitives == reference.num_primitives
    for name, p in resumed.model.params.items():
        assert torch.equal(p.detach(), ref_params[name]), name


def test_interrupt_inside_a_step_keeps_last_checkpoint(tmp_path):
    seen = {}

    @register_loss("_test_interrupt", outputs=("rgb",), weight=1e-9)
    def interrupt(render_out, batch, model, step):
        if step == 25:
            raise KeyboardInterrupt
        return render_out.rgb.mean()

    def remember(trainer, step, info):
        if step == 22:  # after the step-20 checkpoint
            seen["digest"] = _digest(tmp_path / "checkpoint.pt")

    try:
        overrides = quick_overrides(tmp_path, STEPS, **{"train.checkpoint_every": 10, "losses._test_interrupt": 1e-9})
        trainer = Trainer(None, overrides=overrides, callbacks=[remember], quiet=True)
        with pytest.raises(KeyboardInterrupt):
            trainer.fit()
    finally:
        unregister_loss("_test_interrupt")
    assert _digest(tmp_path / "checkpoint.pt") == seen["digest"]
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == 20
    assert not list(tmp_path.glob(".*.tmp"))
    assert not (tmp_path / "metrics.json").exists()


# foreach: the check reads its flag before the optimizer step; fused: it is deferred (Adam skips the step on the
# device, the next step's check raises for it; train/guard.py StepGuard), as on a GPU. Both name the same step.
ADAM_KERNELS = pytest.mark.parametrize("adam_kernel", ["foreach", "fused"])


@ADAM_KERNELS
def test_nan_parameter_is_named_and_checkpoint_kept(tmp_path, adam_kernel):
    seen = {}

    def poison(trainer, step, info):
        if step == 6:  # after the step-5 checkpoint
            seen["digest"] = _digest(tmp_path / "checkpoint.pt")
            with torch.no_grad():
                trainer.model.params["log_scales"][3, 0] = float("nan")

    overrides = quick_overrides(tmp_path, STEPS, **{"train.checkpoint_every": 5, "optim.adam_kernel": adam_kernel})
    with pytest.raises(NonFiniteError) as e:
        Trainer(None, overrides=overrides, callbacks=[poison], quiet=True).fit()
    assert e.value.name == "log_scales" and e.value.step == 7
    assert "log_scales" in str(e.value)
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == 5
    assert _digest(tmp_path / "checkpoint.pt") == seen["digest"]
    assert not (tmp_path / "point_cloud.ply").exists()


@ADAM_KERNELS
def test_nan_gradient_is_named_and_never_applied(tmp_path, adam_kernel):
    @register_loss("_test_nan_grad", outputs=("rgb",))
    def nan_grad(render_out, batch, model, step):
        scale = 0.0 if step == 3 else 1.0
        return torch.sqrt(model.params["quats"][0, 0] * scale).clamp_max(0.0)  # finite value, NaN gradient at 3

    before = {}

    def keep(trainer, step, info):
        if step == 2:  # the parameters the failing step started from
            before.update({n: p.detach().clone() for n, p in trainer.model.params.items()})

    try:
        overrides = quick_overrides(tmp_path, 10, **{"losses._test_nan_grad": 1.0, "optim.adam_kernel": adam_kernel})
        trainer = Trainer(None, overrides=overrides, callbacks=[keep], quiet=True)
        with pytest.raises(NonFiniteError, match=r"step 3: gradient of 'quats' is not finite") as e:
            trainer.fit()
    finally:
        unregister_loss("_test_nan_grad")
    assert e.value.name == "quats"
    for name, p in trainer.model.params.items():  # step 3 never reached the parameters (nor did step 4, if deferred)
        assert torch.equal(p.detach(), before[name]), name


def test_resume_without_checkpoint_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        Trainer(None, overrides=quick_overrides(tmp_path, 5), resume=True, quiet=True)


def test_cli_train_then_resume_with_more_steps(tmp_path, capsys):
    import json

    from warpgs.cli.commands import train_main

    assert train_main(quick_overrides(tmp_path, 8) + ["--quiet"]) == 0
    assert f"results in {tmp_path.resolve()}" in capsys.readouterr().out
    # No CONFIG: --resume continues with the run's saved config.yaml plus the overrides given.
    assert train_main(["--out", str(tmp_path), "--resume", "steps=12", "--quiet"]) == 0
    assert json.loads((tmp_path / "metrics.json").read_text())["steps"] == 12
    assert train_main(["--out", str(tmp_path / "nothing"), "--resume", "--quiet"]) == 2
    assert "no checkpoint" in capsys.readouterr().err
