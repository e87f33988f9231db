"""train.profile_phases: each step's time split by phase (train/phase_timer.py), reported per rank in metrics.json;
off by default, when the timer records nothing."""
import json

import pytest

from warpgs.data.formats.synthetic import RigSettings, write_synthetic_scene
from warpgs.train.phase_timer import PhaseTimer
from warpgs.train.trainer import Trainer

PHASES = ["draw_views", "render_backward", "all_reduce", "optimizer", "densify", "zero_grad"]


def test_the_timer_splits_the_time_between_marks(monkeypatch):
    clock = iter([10.0, 10.5, 12.0, 20.0, 20.25, 21.0])
    monkeypatch.setattr("warpgs.train.phase_timer.time.perf_counter", lambda: next(clock))
    timer = PhaseTimer("cpu", enabled=True)
    for _ in range(2):
        timer.start()
        timer.mark("a")
        timer.mark("b")
        timer.end_step()
    assert timer.summary() == {"steps": 2, "ms_per_step": {"a": 375.0, "b": 1125.0}}
    off = PhaseTimer("cpu", enabled=False)
    off.start()
    off.mark("a")
    off.end_step()
    assert off.summary() == {} and off.steps == 0


@pytest.mark.parametrize("on", [True, False])
def test_a_profiled_run_reports_its_phases(tmp_path, on):
    scene = write_synthetic_scene(tmp_path / "scene", "orbit", RigSettings(width=32, height=24, n_orbit=8),
                                  n_points=200)
    out = tmp_path / "run"
    trainer = Trainer(None, overrides=[f"data.path={scene}", f"output.dir={out}", "train.steps=6", "train.device=cpu",
                                       "train.progress=false", "eval.every=0", "eval.lpips=false",
                                       "strategy.refine_start=2", "strategy.refine_every=2",
                                       f"train.profile_phases={str(on).lower()}"], quiet=True)
    trainer.fit()
    metrics = json.loads((out / "metrics.json").read_text())
    if not on:
        assert "phases" not in metrics
        return
    (split,) = metrics["phases"]  # one rank
    assert split["steps"] == 6 and list(split["ms_per_step"]) == PHASES
    assert all(v >= 0 for v in split["ms_per_step"].values()) and split["ms_per_step"]["render_backward"] > 0
