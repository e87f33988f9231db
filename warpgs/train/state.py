"""A run's checkpoint: which part owns each key (TrainingState), writing it and putting it back (Checkpointer).
The file format itself (atomic write, RNG states) is train/checkpoint.py."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import torch
from torch import nn

from warpgs.train import checkpoint as ckpt
from warpgs.train import sharded_checkpoint as sharded
from warpgs.train.guard import NonFiniteError
from warpgs.model.gaussians import GaussianModel


@dataclass
class RunCounters:
    """Where a run is: steps done, seconds spent inside steps, the total loss of the last step (`loss()`: read from
    the last step's info only when asked for, so a GPU step need not wait for it)."""
    step: int = 0
    train_seconds: float = 0.0
    last_loss: Optional[float] = None
    last_info: Optional[dict] = field(default=None, repr=False, compare=False)

    def loss(self) -> Optional[float]:
        if self.last_info is not None:
            self.last_loss, self.last_info = self.last_info["loss"], None
        return self.last_loss


@dataclass
class TrainingState:
    """Everything a checkpoint holds, as the objects that own it (keys in brackets):
    counters [step, train_seconds, last_loss], model [model], optimizer [optimizer] and module_optimizer
    [module_optimizer] (None without modules), modules [modules], strategy [strategy], extensions [extensions],
    views: a TrainViews [view_generator, view_queue], evaluator: an Evaluator [history], config [config],
    best: a BestState [best_state]; plus the global RNG states [rng]."""
    counters: RunCounters
    model: GaussianModel
    optimizer: torch.optim.Optimizer
    module_optimizer: Optional[torch.optim.Optimizer]
    modules: nn.ModuleDict
    strategy: object  # DensifyStrategy, or anything with state_dict / load_state_dict
    extensions: Sequence
    views: object  # TrainViews
    evaluator: object  # Evaluator
    config: object  # Config
    best: object = None  # a BestState [best_state] (train.steps=auto with schedule.keep_best; None: not kept)


class Checkpointer:
    """checkpoint.pt of one run. Owns its path and `last_step`: the step of the checkpoint on disk that this run
    wrote or resumed from (-1: none yet). `guard` (a NonFiniteGuard, or None with train.nan_guard off) checks the
    parameters before a write, so a broken state never replaces a good checkpoint. write=False (the ranks other
    than 0 of a distributed run, whose state is the same) checks and counts but leaves the file to rank 0."""

    def __init__(self, path, device, *, guard=None, write: bool = True):
        self.path = Path(path)
        self.device = torch.device(device)
        self.guard = guard
        self.write = bool(write)
        self.last_step = -1

    def state_dict(self, parts: TrainingState) -> dict:
        c = parts.counters
        return {"step": c.step, "model": parts.model.to_dict(), "optimizer": parts.optimizer.state_dict(),
                "module_optimizer": None if parts.module_optimizer is None else parts.module_optimizer.state_dict(),
                "modules": parts.modules.state_dict(), "strategy": _to_cpu(parts.strategy.state_dict()),
                "extensions": {f"{i}:{e.name}": e.state_dict() for i, e in enumerate(parts.extensions)},
                "rng": ckpt.rng_state(), **parts.views.state_dict(), "train_seconds": c.train_seconds,
                **parts.evaluator.state_dict(), "last_loss": c.loss(), "config": parts.config.to_dict(),
                "best_state": None if parts.best is None else parts.best.state_dict()}

    def save(self, parts: TrainingState) -> Path:
        step = parts.counters.step
        if self.guard is not None:
            self.guard.check(step)
        if self.write:
            ckpt.save_checkpoint(self.path, self.state_dict(parts))
            sharded.remove_other_steps(self.path, None)  # the shards of an earlier sharded save, if any
        self.last_step = step
        return self.path

    def save_sharded(self, parts: TrainingState, ranks) -> Path:
        """train.parallel=model: this rank's share (parts hold it) into its own shard file, then rank 0's index in
        place of checkpoint.pt (train/sharded_checkpoint.py). A collective: every rank calls it. A non-finite
        share stops every rank (naming it there), so no rank is left waiting for a shard that never comes."""
        step = parts.counters.step
        problem = None
        if self.guard is not None:
            try:
                self.guard.check(step)
            except NonFiniteError as e:
                problem = e
        problems = ranks.all_gather_object(None if problem is None else (problem.name, str(problem)),
                                           what=f"checking the shares of step {step} before saving")
        if problem is not None:
            raise problem
        other = next((p for p in problems if p is not None), None)
        if other is not None:
            raise NonFiniteError(step, other[0], f"another rank's share is not finite ({other[1]})")
        ckpt.save_checkpoint(sharded.shard_file(self.path, step, ranks.rank, ranks.world_size), self.state_dict(parts))
        # Returns once every rank has written its shard: only then may the index name them.
        rows = ranks.all_gather_object(parts.model.num_primitives, what=f"writing the shards of step {step}")
        if ranks.is_main:
            ckpt.save_checkpoint(self.path, sharded.index_state(self.path, step, rows))
            sharded.remove_other_steps(self.path, step)
        self.last_step = step
        return self.path

    def load(self) -> dict:
        """The checkpoint at `path`, for a resume (a clear error when there is none)."""
        if not self.path.is_file():
            raise FileNotFoundError(f"--resume: no checkpoint at {self.path}")
        return ckpt.load_checkpoint(self.path)

    def model_from(self, state: dict, device=None) -> GaussianModel:
        return GaussianModel.from_dict(state["model"], device=self.device if device is None else device)

    def restore(self, state: dict, parts: TrainingState) -> None:
        """Put a loaded checkpoint back into the parts (the model itself was built from it by model_from)."""
        parts.counters.step = int(state["step"])
        parts.optimizer.load_state_dict(state["optimizer"])
        names = [g.get("name") for g in parts.optimizer.param_groups]
        if names != list(parts.model.params):
            raise ValueError(f"checkpoint: optimizer groups {names} do not match the model {list(parts.model.params)}")
        if state.get("modules"):
            parts.modules.load_state_dict(state["modules"])
        if state.get("module_optimizer") is not None and parts.module_optimizer is not None:
            parts.module_optimizer.load_state_dict(state["module_optimizer"])
        strat = {k: (v.to(self.device) if torch.is_tensor(v) and k != "generator" else v)
                 for k, v in state["strategy"].items()}
        parts.strategy.load_state_dict(strat)
        for ext, saved in zip(parts.extensions, state.get("extensions", {}).values()):
            ext.load_state_dict(saved)
        ckpt.set_rng_state(state["rng"])
        try:
            parts.views.load_state_dict(state)
        except ValueError as e:  # a checkpoint this run cannot continue: name it
            raise ValueError(f"{self.path}: {e}") from e
        parts.counters.train_seconds = float(state.get("train_seconds", 0.0))
        parts.evaluator.load_state_dict(state)
        parts.counters.last_loss, parts.counters.last_info = state.get("last_loss"), None
        if parts.best is not None:
            parts.best.load_state_dict(state.get("best_state"))
        self.last_step = parts.counters.step


def _to_cpu(state: dict) -> dict:
    return {k: (v.detach().cpu() if torch.is_tensor(v) else v) for k, v in state.items()}
