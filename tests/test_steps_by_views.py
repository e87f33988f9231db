"""train.steps=by_views (train/steps_by_views.py): a fixed step count from the training views."""
from pathlib import Path

import pytest
from test_sparse_train import run, tiny_lightfield

from warpgs.config import ConfigError, load_config
from warpgs.train.steps_by_views import fixed_steps, steps_by_views, steps_note

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_the_count_grows_with_the_views_between_its_bounds():
    assert [steps_by_views(n) for n in (1, 3, 6, 9, 10, 12, 13, 24, 29, 30, 300)] == \
        [1000, 1000, 1000, 1000, 3000, 4000, 4000, 8000, 9000, 10000, 10000]
    assert fixed_steps("by_views", 12) == 4000 and fixed_steps(1234, 12) == 1234
    assert steps_note("by_views", 4000, 12) == "4000 steps (train.steps=by_views: 12 training views)"
    assert steps_note(4000, 4000, 12) == "4000 steps"


def test_the_config_takes_the_keyword_and_names_it_in_errors():
    assert load_config(None, ["train.steps=by_views"]).train.steps == "by_views"
    assert load_config(None, ["steps=BY_VIEWS"]).train.steps == "by_views"
    with pytest.raises(ConfigError, match=r"train.steps.*'by_views'"):
        load_config(None, ["train.steps=views"])


def test_the_sparse_presets_count_their_steps_from_the_views():
    for preset in ("sparse_llff", "sparse_llff_baseline"):
        assert load_config(CONFIGS / f"{preset}.yaml").train.steps == "by_views"


def test_a_run_with_by_views_trains_the_steps_its_views_ask_for(tmp_path, monkeypatch):
    # The tiny light field has 9 training views: 1000 steps, fixed when the scene loads (a dropout ramp needs that);
    # with the few-view bound lowered, 9 views count as three threes.
    from warpgs.train import steps_by_views
    trainer = run(tmp_path / "nine", "train.steps=by_views", "train.drop_rate=0.1", "train.drop_schedule=ramp")
    assert len(trainer.scene.train) == 9 and trainer.max_steps == 1000 and not trainer.auto_steps
    monkeypatch.setattr(steps_by_views, "FEW_VIEWS", 6)
    trainer = run(tmp_path / "more", "train.steps=by_views")
    assert trainer.max_steps == trainer.strategy.schedule.run_steps == 3000


def test_a_by_views_run_says_its_count_finishes_and_reloads(tmp_path, monkeypatch, capsys):
    # A 2-step count (the bounds lowered) keeps the run short: the start line names the rule, the run ends at its
    # count, and its folder reloads (config.yaml keeps "by_views") at the same count for rendering and evaluation.
    from warpgs.cli.commands import load_run
    from warpgs.train import steps_by_views
    from warpgs.train.trainer import Trainer

    monkeypatch.setattr(steps_by_views, "LEAST_STEPS", 2)
    out = tmp_path / "run"
    overrides = [f"data.path={tiny_lightfield()}", "data.depth_priors=priors", "train.steps=by_views",
                 "train.device=cpu", "train.progress=false", "train.checkpoint_every=0", "eval.every=0",
                 "eval.lpips=false", "eval.save_images=false", "model.sh_degree=0", "strategy.max_primitives=2000",
                 f"output.dir={out}"]
    result = Trainer(CONFIGS / "sparse_lightfield.yaml", overrides=overrides).fit()
    assert result.steps == 2
    assert "2 steps (train.steps=by_views: 9 training views)" in capsys.readouterr().err
    assert "steps: by_views" in (out / "config.yaml").read_text()
    reloaded = load_run(out)
    assert reloaded.max_steps == reloaded.step == 2
