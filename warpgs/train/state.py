"""The trainer's checkpoints: what one holds (model, optimizers, strategy, RNG, step) and how a resume restores it."""
from __future__ import annotations

from pathlib import Path

import torch

from warpgs.train import checkpoint as ckpt


class TrainerCheckpointMixin:
    """Part of `warpgs.train.trainer.Trainer` (uses its model, optimizers, modules, strategy, extensions and RNG state)."""

    # ----- checkpoints ----------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"step": self.step, "model": self.model.to_dict(), "optimizer": self.optimizer.state_dict(),
                "module_optimizer": None if self.module_optimizer is None else self.module_optimizer.state_dict(),
                "modules": self.modules.state_dict(), "strategy": _to_cpu(self.strategy.state_dict()),
                "extensions": {f"{i}:{e.name}": e.state_dict() for i, e in enumerate(self.extensions)},
                "rng": ckpt.rng_state(), "view_generator": self.view_generator.get_state(),
                "view_queue": list(self._queue), "train_seconds": self.train_seconds, "history": self.history,
                "last_loss": self.last_loss, "config": self.config.to_dict()}

    def save_checkpoint(self) -> Path:
        if not self._at_boundary:
            raise RuntimeError("save_checkpoint: only between steps")
        if self.config.train.nan_guard:
            self.check_finite(self.step)  # never replace a good checkpoint with a broken one
        path = ckpt.save_checkpoint(self.checkpoint_path, self.state_dict())
        self._checkpoint_step = self.step
        return path

    def _load_state(self, state: dict) -> None:
        self.step = int(state["step"])
        self.optimizer.load_state_dict(state["optimizer"])
        names = [g.get("name") for g in self.optimizer.param_groups]
        if names != list(self.model.params):
            raise ValueError(f"checkpoint: optimizer groups {names} do not match the model {list(self.model.params)}")
        if state.get("modules"):
            self.modules.load_state_dict(state["modules"])
        if state.get("module_optimizer") is not None and self.module_optimizer is not None:
            self.module_optimizer.load_state_dict(state["module_optimizer"])
        strat = {k: (v.to(self.device) if torch.is_tensor(v) and k != "generator" else v)
                 for k, v in state["strategy"].items()}
        self.strategy.load_state_dict(strat)
        saved_ext = list(state.get("extensions", {}).values())
        for ext, s in zip(self.extensions, saved_ext):
            ext.load_state_dict(s)
        ckpt.set_rng_state(state["rng"])
        self.view_generator.set_state(state["view_generator"])
        self._queue = list(state["view_queue"])
        self.train_seconds = float(state.get("train_seconds", 0.0))
        self.history = list(state.get("history", []))
        self.last_loss = state.get("last_loss")
        self._checkpoint_step = self.step


def _to_cpu(state: dict) -> dict:
    return {k: (v.detach().cpu() if torch.is_tensor(v) else v) for k, v in state.items()}
