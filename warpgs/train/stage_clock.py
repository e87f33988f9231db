"""Wall seconds of a run's one-off stages: the set-up before the first step (joining the ranks, loading the scene
and its priors, building the model from its initial points, loading the training views, sharing the model out) and
the outputs after the last (checkpoint and PLY, the final evaluation), and what runs between steps outside their clock
(the periodic evaluations, train.steps=auto's validations), summed. metrics.json's "stage_seconds" lists them, so
a run's wall time beyond its training time can be read stage by stage (issue 33: the start-up that does not shrink
with the GPU count). Host wall time; GPU work still queued when a stage ends is counted where it is waited for."""
from __future__ import annotations

import contextlib
import time
from typing import Dict


class StageClock:
    def __init__(self):
        self.seconds: Dict[str, float] = {}  # in first-timed order

    @contextlib.contextmanager
    def stage(self, name: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = round(self.seconds.get(name, 0.0) + time.perf_counter() - start, 3)
