"""The best validated state of a `train.steps=auto` run, so that the run can end from it (train/schedule.py).

On captures of a few dozen views the held-out quality can fall after its peak and not come back before the rule
stops the run: phone64 on an H100, 3 seeds, the validation best at step 3000 (just before the first opacity
reset) for two of them, and their ends at step 8000 0.65 and 0.92 dB below step 3000 on the test views. So every
new best validation score copies the model's parameters with their optimizer state (and the modules with theirs)
into CPU memory (the parameters into reused page-locked buffers, without stalling the GPU: train/host_copies.py);
when the rule starts the polish and the latest score is more than schedule.min_gain below the best, the run goes
back to that copy and polishes it (`schedule.keep_best`, on by default).

Checkpoints carry the copy (single-process and data-parallel runs), so a resumed run ends as the uninterrupted one
would; model-parallel runs keep it in memory only (a shard's rows do not survive a change of rank count)."""
from __future__ import annotations

from typing import Optional

import torch

from warpgs.train.host_copies import HostCopies
from warpgs.train.optim import copy_parameters, load_parameters


class BestState:
    """The copy of the best validated step (step None: none taken yet)."""

    def __init__(self):
        self.step: Optional[int] = None
        self.params: Optional[dict] = None  # optim.copy_parameters of the model and its optimizer
        self.modules: Optional[dict] = None  # the modules' state_dict, and their optimizer's
        self.module_optimizer: Optional[dict] = None
        self._host = HostCopies()  # the buffers self.params lives in (kept from one best to the next)

    @torch.no_grad()
    def capture(self, step: int, parts) -> None:
        """Copy the model, its optimizer state and the modules of `parts` (a TrainingState) as step `step`'s."""
        self.step = int(step)
        self.params = copy_parameters(parts.model, parts.optimizer, copy=self._host.copy)
        self.modules = _cpu(parts.modules.state_dict()) if len(parts.modules) else None
        opt = parts.module_optimizer
        self.module_optimizer = None if opt is None else _cpu(opt.state_dict())

    @torch.no_grad()
    def restore(self, parts) -> None:
        """Put the copy back into `parts`: the model's rows (their count may differ from now) with their optimizer
        state, the modules, and the densification statistics sized to the restored model (zeroed)."""
        if self.params is None:
            raise RuntimeError("BestState.restore: nothing was captured")
        self._host.wait()
        load_parameters(parts.model, parts.optimizer, self.params)
        if self.modules is not None:
            parts.modules.load_state_dict(self.modules)
        if self.module_optimizer is not None and parts.module_optimizer is not None:
            parts.module_optimizer.load_state_dict(self.module_optimizer)
        parts.strategy.initialize(parts.model)

    def state_dict(self) -> Optional[dict]:
        if self.step is None:
            return None
        self._host.wait()  # the copies are views of larger reused buffers: a checkpoint gets their own tensors
        return {"step": self.step, "params": _cpu(self.params), "modules": self.modules,
                "module_optimizer": self.module_optimizer}

    def load_state_dict(self, state: Optional[dict]) -> None:
        self.__init__()
        if state:
            self.step, self.params = int(state["step"]), state["params"]
            self.modules, self.module_optimizer = state.get("modules"), state.get("module_optimizer")


def _cpu(obj):
    """A copy of a (nested) state dict with every tensor copied into CPU memory (containers rebuilt, so nothing is
    shared with the live state)."""
    if torch.is_tensor(obj):
        return obj.detach().to("cpu", copy=True)
    if isinstance(obj, dict):
        return type(obj)((k, _cpu(v)) for k, v in obj.items())
    if isinstance(obj, (list, tuple)):
        return type(obj)(_cpu(v) for v in obj)
    return obj
