"""benchmarks/step_slack.py: reading a step's GPU slack off its sleep curve."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import step_slack  # noqa: E402


def test_a_gpu_bound_step_grows_by_every_sleep():
    found = step_slack.slack_summary([(0, 5.0), (500, 5.5), (1000, 6.0)])
    assert [share for _, share in found["added_share"]] == pytest.approx([1.0, 1.0])
    assert found["absorbed_up_to_us"] == 0


def test_a_host_bound_step_absorbs_sleeps_up_to_its_idle_time():
    # 1.2 ms idle a step: 500 and 1000 us vanish in it, 2000 us shows its excess (0.8 ms)
    found = step_slack.slack_summary([(0, 5.0), (500, 5.02), (1000, 5.05), (2000, 5.8)])
    assert found["absorbed_up_to_us"] == 1000
    assert found["added_share"][-1][1] == pytest.approx(0.4)


def test_it_refuses_to_run_without_a_gpu(monkeypatch):
    monkeypatch.setattr(step_slack.torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit, match="needs a CUDA device"):
        step_slack.main(["data/none"])
