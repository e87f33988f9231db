"""Figures the GPU benchmarks derive from their runs: the distributed benchmark's rate after start-up, the
real-capture benchmark's evaluation period and the raster benchmark's spread of its ratios to gsplat (all computed on
the CPU from stored numbers)."""
import math
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import distributed  # noqa: E402
import raster  # noqa: E402
import real_capture  # noqa: E402
import train_compare  # noqa: E402


def _evals(points):
    return [{"step": v, "views_seen": v, "psnr": 20.0, "train_seconds": t} for v, t in points]


def test_steady_rate_leaves_out_the_first_interval():
    # 250 views in 6 s (start-up included), then 250 views every 4 s.
    evals = _evals([(250, 6.0), (500, 10.0), (750, 14.0)])
    assert distributed.steady_views_per_s(evals) == pytest.approx(500 / 8.0)
    whole = 750 / 14.0
    assert distributed.steady_views_per_s(evals) > whole


def test_steady_rate_needs_two_evaluations():
    assert distributed.steady_views_per_s(_evals([(250, 6.0)])) is None
    assert distributed.steady_views_per_s([]) is None


@pytest.mark.parametrize("every, marks, period", [(5000, [7000, 30000], 1000), (1000, [7000], 1000),
                                                  (1000, [500], 500), (5000, [30000], 5000)])
def test_every_mark_is_an_evaluation_step(every, marks, period):
    got = real_capture.evaluation_period(every, marks)
    assert got == period
    assert all(m % got == 0 for m in marks) and every % got == 0


def test_marks_without_a_useful_common_period_are_refused(tmp_path):
    with pytest.raises(SystemExit, match="lands on every mark is 1 steps"):
        real_capture.main([str(tmp_path), "--steps", "7001", "--eval-every", "1000"])


def test_an_auto_run_keeps_the_bound_an_override_names():
    marks = [7000, 30000]
    assert real_capture.auto_bound(30000, ["data.downscale=2"], marks) == 30000
    assert real_capture.auto_bound(20000, [], marks) == 20000  # the preset's bound: the default a user gets
    assert real_capture.auto_bound(30000, [], [7000]) == 7000
    assert real_capture.auto_bound(20000, ["schedule.max_steps=20000"], marks) == 20000
    with pytest.raises(SystemExit, match="schedule.max_steps=40000.*largest --steps mark"):
        real_capture.auto_bound(40000, ["schedule.max_steps = 40000"], marks)


def test_each_evaluation_is_echoed_once_as_it_happens(capsys):
    from types import SimpleNamespace

    trainer = SimpleNamespace(history=[])
    echo = train_compare.echo_evaluations()
    echo(trainer, 0, {})
    trainer.history.append({"step": 1000, "train_seconds": 12.34, "psnr": 23.4567, "num_primitives": 8674})
    echo(trainer, 1000, {})
    echo(trainer, 1001, {})
    assert capsys.readouterr().out == ("warpgs evaluated at step 1000: 23.457 dB held-out, 8674 primitives, "
                                       "12.3 s of training\n")


def test_the_raster_ratio_spread_pairs_the_rounds():
    # Round by round 1.1 and 0.9 of gsplat's time: mean 1.0, standard error 0.1 (sd 0.1414 over 2 rounds).
    assert abs(raster.round_ratio_se([1.1, 1.8], [1.0, 2.0]) - 0.1) < 1e-12
    # A slow moment that hits both systems alike leaves no spread in the ratio.
    assert raster.round_ratio_se([1.0, 3.0, 2.0], [0.5, 1.5, 1.0]) == 0.0
    assert math.isnan(raster.round_ratio_se([1.0], [1.0]))
