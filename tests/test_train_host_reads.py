"""A training step reads nothing back from its device while it runs, so that on a GPU the host never waits for the
backward (train/guard.py StepGuard, train/step_info.py StepInfo). Checked on the CPU by counting the calls that
would be host reads on a GPU: item / float / bool of a tensor (aten::_local_scalar_dense), tolist and numpy. With
fused Adam (the CUDA default, here forced) the one read a step is the NaN guard's flags of the step before, which a
GPU has finished by then."""
import traceback
from collections import Counter
from pathlib import Path

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from train_fixtures import quick_overrides
from warpgs.train.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]


class HostReads(TorchDispatchMode):
    """Counts host reads by the warpgs function that made them."""

    def __init__(self):
        super().__init__()
        self.sites = Counter()
        self._tolist, self._numpy = torch.Tensor.tolist, torch.Tensor.numpy

    def _note(self, kind):
        # The innermost warpgs function that asked (HostCopy, train/step_info.py, only carries out the read).
        frames = [f for f in traceback.extract_stack() if "/warpgs/" in f.filename and "/tests/" not in f.filename
                  and not f.filename.endswith("step_info.py")]
        self.sites[(kind, frames[-1].name if frames else "?")] += 1

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func.overloadpacket.__name__ == "_local_scalar_dense":
            self._note("item")
        return func(*args, **(kwargs or {}))

    def __enter__(self):
        mode, tolist, numpy = self, self._tolist, self._numpy
        torch.Tensor.tolist = lambda t, *a: (mode._note("tolist"), tolist(t, *a))[1]
        torch.Tensor.numpy = lambda t, *a, **k: (mode._note("numpy"), numpy(t, *a, **k))[1]
        return super().__enter__()

    def __exit__(self, *exc):
        torch.Tensor.tolist, torch.Tensor.numpy = self._tolist, self._numpy
        return super().__exit__(*exc)


# default: with the environment module's optimizer; a batch of two views: its means on the device for the guard.
@pytest.mark.parametrize("preset,batch", [("default", 1), ("surfels", 1), ("default", 2)])
def test_a_densifying_step_reads_back_only_the_previous_steps_guard_flags(tmp_path, preset, batch):
    # Densifying (statistics every step) but no refine in the counted steps: a refine reads counts, every 100 steps.
    overrides = quick_overrides(tmp_path, 100, **{"optim.adam_kernel": "fused", "strategy.refine_start": 1,
                                                  "strategy.refine_every": 1000, "train.batch_size": batch})
    trainer = Trainer(str(ROOT / "configs" / f"{preset}.yaml"), overrides=overrides, quiet=True)
    for _ in range(3):
        trainer.train_step()
    steps = 5
    with HostReads() as reads:
        infos = [trainer.train_step() for _ in range(steps)]
    assert trainer.strategy.schedule.densifying(trainer.step - 1)
    # The epoch's shuffle (TrainViews.draw: a CPU generator's randperm) is no device read either.
    other = {site: n for site, n in reads.sites.items() if site not in {("tolist", "raise_if_failed"),
                                                                          ("tolist", "draw")}}
    assert reads.sites[("tolist", "raise_if_failed")] == steps and other == {}, reads.sites
    assert all(info.pending is False for info in infos)  # on the CPU the values are there; they were not read
    assert infos[-1]["loss"] > 0  # and read on demand


@pytest.mark.parametrize("preset", ["default", "surfels"])
def test_the_deferred_guard_keeps_no_autograd_graph_into_the_next_step(tmp_path, preset):
    """The pending check holds the step's loss values, not its graph, and the renders hand their buffer set back
    after their backward: one set serves every step."""
    from warpgs.render import device_state

    device_state.release_workspaces()  # this thread's pool starts empty
    overrides = quick_overrides(tmp_path, 100, **{"optim.adam_kernel": "fused"})
    trainer = Trainer(str(ROOT / "configs" / f"{preset}.yaml"), overrides=overrides, quiet=True)
    for _ in range(4):
        trainer.train_step()
    pending = trainer.step_guard.pending
    assert pending is not None and pending.result.total.grad_fn is None
    assert len(device_state.device_state(trainer.device).ws._free_frames) == 1


def test_a_batch_of_views_renders_each_into_the_same_buffer_set(tmp_path):
    """A view's pass keeps its losses without their graph, and its render's buffer set is back in the pool for the
    next view of the same step: a batch of two views leaves one set in the pool, as one view does."""
    from warpgs.render import device_state

    device_state.release_workspaces()  # this thread's pool starts empty
    overrides = quick_overrides(tmp_path, 100, **{"optim.adam_kernel": "fused", "train.batch_size": 2})
    trainer = Trainer(str(ROOT / "configs" / "default.yaml"), overrides=overrides, quiet=True)
    for _ in range(4):
        trainer.train_step()
    assert len(device_state.device_state(trainer.device).ws._free_frames) == 1
