"""train.profile_phases: where a training step's time goes, phase by phase (drawing the views, rendering and
back-propagating them, the all-reduce, the optimizer, densification, clearing gradients).

Off by default. When on, the device is synchronised at every phase boundary, so each phase's GPU work is counted in
that phase and not in a later one that waits for it; the steps get a little slower, so a profiled run measures
where the time goes, not how fast training is (benchmarks/distributed.py --phases runs one of each).
"""
from __future__ import annotations

import time
from typing import Dict

import torch


class PhaseTimer:
    def __init__(self, device, enabled: bool):
        self.device = torch.device(device)
        self.enabled = bool(enabled)
        self.seconds: Dict[str, float] = {}  # in first-marked order
        self.steps = 0
        self._last = 0.0

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def start(self) -> None:
        """At the top of a step."""
        if self.enabled:
            self._sync()
            self._last = time.perf_counter()

    def mark(self, phase: str) -> None:
        """The time since the previous mark (or start) goes to `phase`."""
        if self.enabled:
            self._sync()
            now = time.perf_counter()
            self.seconds[phase] = self.seconds.get(phase, 0.0) + now - self._last
            self._last = now

    def end_step(self) -> None:
        if self.enabled:
            self.steps += 1

    def summary(self) -> dict:
        """{"steps": n, "ms_per_step": {phase: mean milliseconds}} (empty when off or before any step)."""
        if not self.enabled or not self.steps:
            return {}
        return {"steps": self.steps,
                "ms_per_step": {k: round(1e3 * v / self.steps, 4) for k, v in self.seconds.items()}}
