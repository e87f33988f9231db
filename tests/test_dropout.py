"""Primitive dropout in training renders (train.drop_rate, train/dropout.py)."""
import math

import pytest
import torch
from test_sparse_train import run

from warpgs.config import ConfigError
from warpgs.train.dropout import dropped_opacities


def test_a_share_is_dropped_and_the_rest_compensated():
    torch.manual_seed(0)
    opacities = torch.rand(200_000, 1, requires_grad=True)
    out = dropped_opacities(opacities, 0.2)
    dropped = out.detach()[:, 0] == 0
    assert abs(dropped.double().mean().item() - 0.2) < 0.005
    kept = ~dropped
    torch.testing.assert_close(out.detach()[kept], opacities.detach()[kept] / 0.8)
    out.sum().backward()  # the kept rows' gradient is the compensation, the dropped rows' zero
    assert torch.allclose(opacities.grad[kept], torch.full_like(opacities.grad[kept], 1.25))
    assert not opacities.grad[dropped].any()
    assert dropped_opacities(opacities, 0.0) is opacities


def test_training_renders_drop_and_other_renders_do_not(tmp_path):
    trainer = run(tmp_path, "train.drop_rate=0.5", "strategy.refine_start=1000", steps=4)
    view = trainer.view(trainer.train_indices[0])
    whole = [trainer.render(view, ("rgb",)).rgb for _ in range(2)]
    assert torch.equal(whole[0], whole[1])  # evaluation and outputs render every primitive
    dropped = trainer.render(view, ("rgb",), drop_rate=0.5).rgb
    assert not torch.equal(dropped, whole[0])
    for _ in range(3):
        assert math.isfinite(trainer.train_step()["loss"])


def test_the_config_refuses_a_rate_outside_zero_to_one(tmp_path):
    with pytest.raises(ConfigError, match="train.drop_rate"):
        run(tmp_path, "train.drop_rate=1.0")


def test_auto_drops_with_few_or_many_training_views(tmp_path):
    from warpgs.train.dropout import AUTO_MAX_VIEWS, AUTO_OFF_MAX_VIEWS, AUTO_RATE, AUTO_RATE_3, drop_rate_for

    assert AUTO_MAX_VIEWS == 4 and AUTO_OFF_MAX_VIEWS == 9 and AUTO_RATE_3 != AUTO_RATE  # rates measured at 3 and 4
    counts = (2, 3, 4, 5, 9, 10, 24)
    assert [drop_rate_for("auto", n) for n in counts] == [AUTO_RATE_3, AUTO_RATE_3, AUTO_RATE, 0.0, 0.0, AUTO_RATE,
                                                           AUTO_RATE]
    assert drop_rate_for("auto", AUTO_OFF_MAX_VIEWS) == 0.0 and drop_rate_for("auto", AUTO_OFF_MAX_VIEWS + 1) > 0
    assert drop_rate_for(0.0, 3) == 0.0 and drop_rate_for(0.3, 30) == 0.3
    # The tiny light field trains on its 3x3 array: 9 views, so "auto" leaves dropout off; with 3 of them, on.
    nine = run(tmp_path / "nine", "train.drop_rate=auto", steps=2)
    assert nine.drop_rate == 0.0
    dropped = [nine.scene.names[v] for v in nine.scene.train[3:]]
    three = run(tmp_path / "three", "train.drop_rate=auto", f"data.exclude=[{', '.join(dropped)}]", steps=2)
    assert len(three.views.indices) == 3 and three.drop_rate == AUTO_RATE_3
    assert math.isfinite(three.train_step()["loss"])
    with pytest.raises(ConfigError, match="train.drop_rate"):
        run(tmp_path / "bad", "train.drop_rate=sometimes")


def test_auto_counts_the_held_out_validation_views_as_training_views(tmp_path):
    # 4 training views with train.steps=auto: one is held out for validation and trains again after the stop, so the
    # few-view rules count 4, as unpooling and the prior points do: dropout at 4 views' rate, no virtual views.
    from warpgs.train.dropout import AUTO_RATE
    from warpgs.train.virtual_views import AUTO_MAX_VIEWS

    nine = run(tmp_path / "nine", steps=2)
    dropped = [nine.scene.names[v] for v in nine.scene.train[4:]]
    four = run(tmp_path / "four", "train.drop_rate=auto", "train.virtual_views=auto", "train.steps=auto",
               f"data.exclude=[{', '.join(dropped)}]")
    assert len(four.scene.train) == 4 and len(four.views.indices) == 3 and len(four.views.held_out) == 1
    assert AUTO_MAX_VIEWS == 3 and four.virtual_every == 0
    assert four.drop_rate == AUTO_RATE


def test_the_start_line_says_whether_auto_turned_dropout_on():
    from warpgs.train.dropout import AUTO_MAX_VIEWS, AUTO_OFF_MAX_VIEWS, dropout_note

    off = dropout_note("auto", 0.0, AUTO_MAX_VIEWS + 1)
    assert "off" in off and f"{AUTO_MAX_VIEWS + 1} training views" in off
    assert f"on with at most {AUTO_MAX_VIEWS} or more than {AUTO_OFF_MAX_VIEWS}" in off
    assert dropout_note("auto", 0.1, 3) == dropout_note(0.1, 0.1, 3) == "; primitive dropout 0.1"
    assert dropout_note(0.0, 0.0, 3) == ""  # not asked for: nothing to explain


def test_a_ramped_rate_rises_from_zero_to_the_rate_at_the_last_step(tmp_path):
    from warpgs.train.dropout import manner_note, rate_at
    assert rate_at(0.2, "constant", 0, 100) == rate_at(0.2, "constant", 99, 100) == 0.2
    ramp = [rate_at(0.2, "ramp", s, 100) for s in range(100)]
    assert ramp[0] == pytest.approx(0.002) and ramp[49] == pytest.approx(0.1) and ramp[-1] == pytest.approx(0.2)
    assert all(a < b for a, b in zip(ramp, ramp[1:]))
    assert rate_at(0.0, "ramp", 50, 100) == 0.0
    assert manner_note("ramp", 0, 0.1) == " ramped up from 0" and manner_note("constant", 0, 0.1) == ""
    assert manner_note("ramp", 0, 0.0) == "" and "unused" in manner_note("ramp", 2, 0.0)
    assert "near primitives more often (power 2)" in manner_note("constant", 2, 0.1)
    trainer = run(tmp_path, "train.drop_rate=0.5", "train.drop_schedule=ramp", "strategy.refine_start=1000", steps=4)
    asked = []  # the rate each training render is given
    render = trainer.render
    trainer.render = lambda *a, drop_rate=0.0, **k: asked.append(drop_rate) or render(*a, drop_rate=drop_rate, **k)
    for _ in range(4):
        trainer.train_step()
    assert asked == pytest.approx([0.125, 0.25, 0.375, 0.5])
    with pytest.raises(ConfigError, match="train.drop_schedule"):
        run(tmp_path / "bad", "train.drop_schedule=linear")
    with pytest.raises(ConfigError, match="train.drop_schedule.*train.steps"):
        run(tmp_path / "auto", "train.drop_rate=0.1", "train.drop_schedule=ramp", "train.steps=auto")


def test_near_primitives_are_left_out_more_often_at_the_same_mean_rate():
    """train.drop_near: in front of the camera the drop probability follows (median depth / depth) ** power, averaging
    the rate, capped; behind the camera the plain rate. Each kept row is compensated by its own 1 - p."""
    from warpgs.train.dropout import MAX_NEAR_PROBABILITY, near_probabilities

    viewmat = torch.eye(4)  # camera at the origin looking down +z
    depth = torch.tensor([0.5, 1.0, 2.0, 4.0, -1.0])
    means = torch.stack([torch.zeros(5), torch.zeros(5), depth], 1)
    p = near_probabilities(means, viewmat, 0.1, 1.0)
    assert p[4] == pytest.approx(0.1)  # behind the camera
    assert torch.all(p[:3] > p[1:4]) and p[:4].mean().item() == pytest.approx(0.1, rel=1e-5)
    assert p[0] / p[3] == pytest.approx(8.0, rel=1e-5)  # proportional to 1 / depth
    steep = near_probabilities(torch.stack([torch.zeros(3), torch.zeros(3), torch.tensor([0.01, 1.0, 1.0])], 1),
                               viewmat, 0.5, 2.0)
    assert steep.max().item() == pytest.approx(MAX_NEAR_PROBABILITY)
    flat = near_probabilities(means, viewmat, 0.1, 0.0)
    torch.testing.assert_close(flat, torch.full((5,), 0.1))
    # A primitive at the camera counts as NEAREST_DEPTH_SHARE of the median: finite, and the rest keep their share.
    crowd = torch.stack([torch.zeros(1000), torch.zeros(1000), torch.cat([torch.tensor([1e-7]), torch.ones(999)])], 1)
    p = near_probabilities(crowd, viewmat, 0.3, 6.0)
    assert torch.isfinite(p).all() and p[0] == pytest.approx(MAX_NEAR_PROBABILITY)
    assert p.mean().item() == pytest.approx(0.3, rel=1e-4)  # what the cap cut went to the others
    torch.manual_seed(0)
    opacities = torch.full((100_000, 1), 0.5, requires_grad=True)
    probs = torch.where(torch.arange(100_000) % 2 == 0, torch.tensor(0.6), torch.tensor(0.1))
    out = dropped_opacities(opacities, 0.35, probs).detach()[:, 0]
    assert abs((out[0::2] == 0).double().mean().item() - 0.6) < 0.01
    assert abs((out[1::2] == 0).double().mean().item() - 0.1) < 0.01
    assert out[0::2].max().item() == pytest.approx(0.5 / 0.4) and out[1::2].max().item() == pytest.approx(0.5 / 0.9)


def test_training_renders_drop_near_primitives_and_the_config_checks_the_power(tmp_path, monkeypatch):
    from warpgs.train import dropout

    seen = []  # (rate, power) of each near_probabilities call the trainer makes
    real = dropout.near_probabilities

    def recording(means, viewmat, rate, power):
        seen.append((rate, power))
        return real(means, viewmat, rate, power)

    monkeypatch.setattr("warpgs.train.trainer.near_probabilities", recording)
    trainer = run(tmp_path, "train.drop_rate=0.3", "train.drop_near=2", "strategy.refine_start=1000", steps=3)
    view = trainer.view(trainer.train_indices[0])
    assert not torch.equal(trainer.render(view, ("rgb",), drop_rate=0.3).rgb, trainer.render(view, ("rgb",)).rgb)
    assert math.isfinite(trainer.train_step()["loss"])
    assert seen and all(s == (0.3, 2.0) for s in seen)  # training renders draw by depth; the plain render does not
    plain = run(tmp_path / "plain", "train.drop_rate=0.3", "strategy.refine_start=1000", steps=3)
    count = len(seen)
    plain.train_step()
    assert len(seen) == count
    with pytest.raises(ConfigError, match="train.drop_near"):
        run(tmp_path / "bad", "train.drop_near=-1")
