"""Shared helpers for the trainer tests: a small synthetic orbit scene rendered once per test process."""
from __future__ import annotations

import atexit
import functools
import shutil
import tempfile
from pathlib import Path

from warpgs.data.formats.synthetic import RigSettings, write_synthetic_scene

_ROOT = Path(tempfile.mkdtemp(prefix="warpgs-train-tests-"))
atexit.register(shutil.rmtree, _ROOT, ignore_errors=True)


@functools.lru_cache(maxsize=None)
def small_orbit() -> Path:
    """16 views at 64x48 around the synthetic objects (LLFF split: 14 train, 2 test), 1500 SfM-like points."""
    return write_synthetic_scene(_ROOT / "orbit64", "orbit", RigSettings(width=64, height=48, n_orbit=16),
                                 n_points=1500)


def quick_overrides(out_dir, steps: int = 40, **extra) -> list:
    """A short CPU run on the small scene: densification early and often, no periodic evaluation."""
    settings = {
        "data.path": str(small_orbit()), "output.dir": str(out_dir), "train.steps": steps, "train.device": "cpu",
        "train.progress": False, "train.checkpoint_every": 0, "eval.every": 0, "eval.lpips": False,
        "model.sh_interval": 15, "strategy.refine_start": 10, "strategy.refine_every": 10,
        "strategy.refine_stop": 1000, "strategy.reset_every": 0, "strategy.max_primitives": 6000,
    }
    settings.update(extra)
    return [f"{k}={'null' if v is None else v}" for k, v in settings.items()]


class Interrupt:
    """A step callback that raises KeyboardInterrupt (a Ctrl-C) once the trainer has done `at` steps."""

    def __init__(self, at):
        self.at = at

    def __call__(self, trainer, step, info):
        if trainer.step == self.at:
            raise KeyboardInterrupt
