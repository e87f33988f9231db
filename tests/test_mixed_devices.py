"""Tensors on two devices at once, as a model-parallel run on GPUs has them when it saves: the model gathered in
CPU memory, the modules (and the collectives' scalars) on the GPU. On a CPU-only machine torch's lazy-tensor
device (its TorchScript backend, a second device that computes on the CPU) stands in for the GPU: combining its
tensors with CPU tensors fails as combining CUDA and CPU tensors does, which the all-CPU gloo tests cannot show
(the first model-parallel run on GPUs stopped at its first checkpoint in NonFiniteGuard.check)."""
import pytest
import torch

from train_fixtures import quick_overrides
from warpgs.train.checkpoint import load_checkpoint
from warpgs.train.distributed import Ranks
from warpgs.train.guard import NonFiniteError, NonFiniteGuard
from warpgs.train.trainer import Trainer


@pytest.fixture(scope="module")
def second_device():
    ts_backend = pytest.importorskip("torch._lazy.ts_backend", reason="this torch has no lazy-tensor backend")
    ts_backend.init()
    device = torch.device("lazy")
    with pytest.raises(RuntimeError):  # what makes it a stand-in: no op mixes it with CPU tensors
        torch.stack([torch.zeros((), device=device), torch.zeros(())])
    return device


def test_the_guard_checks_parameters_on_two_devices(second_device):
    params = {"cpu": torch.nn.Parameter(torch.ones(4)), "other": torch.nn.Parameter(torch.ones(3, device=second_device))}
    params["cpu"].grad = torch.ones(4)
    params["other"].grad = torch.ones(3, device=second_device)
    guard = NonFiniteGuard(lambda: params.items())
    guard.check(5)  # finite everywhere: no error (it used to stack the sums of both devices)
    params["other"].grad = torch.full((3,), float("nan"), device=second_device)
    with pytest.raises(NonFiniteError, match="gradient of 'other'") as err:
        guard.check(6)
    assert err.value.step == 6 and err.value.name == "other"


def test_a_checkpoint_of_a_model_in_cpu_memory_and_modules_elsewhere_saves_and_loads(second_device, tmp_path):
    overrides = quick_overrides(tmp_path / "run", steps=4, **{"extensions.environment.degree": 2})
    tr = Trainer(None, overrides=overrides, quiet=True)
    tr.train_step()
    assert list(tr.modules) == ["environment"]  # a learned sky map: a module trained alongside the model
    tr.modules.to(second_device)  # the model stays in CPU memory, as a gathered model-parallel model does
    path = tr.save_checkpoint()
    saved = load_checkpoint(path, map_location=None)  # as written: every tensor in CPU memory
    for name, p in tr.modules.named_parameters():
        assert saved["modules"][name].device.type == "cpu"
        torch.testing.assert_close(saved["modules"][name], p.detach().cpu(), rtol=0, atol=0)
    assert saved["step"] == 1 and saved["model"]["params"]["means"].shape == tr.model.means.shape
    # A non-finite module on the other device still stops the save, naming it.
    first = next(iter(tr.modules.parameters()))
    with torch.no_grad():
        first.fill_(float("nan"))
    with pytest.raises(NonFiniteError, match="modules."):
        tr.save_checkpoint()


def test_collectives_without_tensors_of_their_own_use_the_ranks_device(second_device, monkeypatch):
    # A model-parallel step all-reduces only the modules' gradients plus the loss scalars; without modules the
    # scalars' buffer must still be on the collectives' device (NCCL takes no CPU tensors).
    import torch.distributed as dist

    seen = []
    monkeypatch.setattr(dist, "all_reduce", lambda t, op=None: seen.append(t.device))
    ranks = Ranks(0, 2, backend="nccl", device=second_device)
    assert ranks.all_reduce_gradients([], [1.0, 2.0], step=3) == [1.0, 2.0]
    assert [d.type for d in seen] == [second_device.type]


def test_a_checkpoint_from_more_gpus_resumes_on_fewer(monkeypatch):
    # A checkpoint holds one CUDA RNG state per GPU its writer saw (two here); a process seeing one GPU sets that
    # one (torch.cuda.set_rng_state_all would ask for the missing second GPU).
    from warpgs.train.checkpoint import rng_state, set_rng_state

    state = rng_state()
    state["cuda"] = [torch.zeros(16, dtype=torch.uint8), torch.ones(16, dtype=torch.uint8)]
    calls = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "set_rng_state", lambda s, device="cuda": calls.append((device, int(s[0]))))
    monkeypatch.setattr(torch.cuda, "set_rng_state_all", lambda states: calls.extend((i, int(s[0])) for i, s in
                                                                                     enumerate(states)))
    set_rng_state(state)
    assert calls == [(0, 0)]
