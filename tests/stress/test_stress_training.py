"""configs/stress.yaml in real training (CPU, small scene): with the NaN guard on, a few hundred steps of the
stressed settings (10x learning rates, SH degree 3 from step 0, densification every 10 steps up to the budget,
opacity resets, near plane at 1e-4, random init with a far shell) must finish every step with finite
parameters, a finite loss and finite metrics, and write the usual outputs. A second test pins the config file
itself, so it cannot quietly drift back towards the defaults and stop stressing anything."""
import json
import math
from pathlib import Path

import pytest
import torch

from train_fixtures import small_orbit
from warpgs.train.checkpoint import load_checkpoint
from warpgs.config.loader import Config, load_config
from warpgs.model.gaussians import SurfelModel, load_ply
from warpgs.train.trainer import NonFiniteError, Trainer

STRESS = Path(__file__).resolve().parents[2] / "configs" / "stress.yaml"
DEFAULT = STRESS.with_name("default.yaml")
STEPS = 300  # 28 refine passes and one opacity reset (step 150); ~14 s on a 2-core CPU
BUDGET = 6000  # 3x the initial 2000 primitives: reached by step ~50, so the budget cut-off runs from then on


def stress_overrides(out_dir, steps: int, **extra) -> list:
    """Only what a CPU test must change: the small scene, fewer initial points and a smaller budget (kept
    above the initial count, so densification has room before the budget bites). Every stressed knob stays."""
    settings = {"data.path": str(small_orbit()), "output.dir": str(out_dir), "train.steps": steps,
                "train.device": "cpu", "train.progress": False, "train.checkpoint_every": 100, "eval.every": 150,
                "model.init_points": 1500, "model.background_points": 500, "strategy.max_primitives": BUDGET}
    settings.update(extra)
    return [f"{k}={v}" for k, v in settings.items()]


def run_stress(out_dir, steps: int, **extra):
    """(trainer, result, per-step infos); a NonFiniteError fails the test with the guard's own diagnosis."""
    infos = []

    def record(trainer, step, info):
        infos.append(dict(info, active_sh_degree=trainer.model.active_sh_degree))

    trainer = Trainer(STRESS, overrides=stress_overrides(out_dir, steps, **extra), callbacks=[record], quiet=True)
    assert trainer.config.train.nan_guard, "the stress run is only meaningful with the NaN guard on"
    try:
        result = trainer.fit()
    except NonFiniteError as e:
        pytest.fail(f"NaN guard stopped the stress run at step {e.step} on {e.name!r}: {e}")
    return trainer, result, infos


def nonfinite(tensors) -> list:
    """Names of the (name, tensor) pairs that hold a NaN or Inf."""
    return [name for name, t in tensors if not bool(torch.isfinite(t.detach()).all())]


@pytest.fixture(scope="module")
def stressed(tmp_path_factory):
    return run_stress(tmp_path_factory.mktemp("stress"), STEPS)


def test_all_steps_run_with_finite_loss(stressed):
    trainer, result, infos = stressed
    assert result.steps == trainer.step == STEPS
    assert [i["step"] for i in infos] == list(range(STEPS))
    bad = [(i["step"], i["loss"]) for i in infos if not math.isfinite(i["loss"])]
    assert not bad, f"non-finite losses: {bad[:5]}"
    assert all(math.isfinite(v) for i in infos for v in i["values"].values())


def test_every_parameter_is_finite(stressed):
    trainer, _, _ = stressed
    names = [n for n, _ in trainer.named_parameters()]
    assert "modules.environment.coeffs" in names  # the learned background is trained (and guarded) too
    assert not nonfinite(trainer.named_parameters())
    trainer.check_finite(trainer.step)  # the guard's own check agrees


def test_the_run_was_actually_stressed(stressed):
    """The settings reached the code they are meant to stress (a config typo or a trainer change that turns
    them off would make the finite result above meaningless)."""
    trainer, result, infos = stressed
    assert infos[0]["active_sh_degree"] == 3  # degree 3 from step 0
    reports = [i["densify"] for i in infos if i["densify"]]
    refines = [r for r in reports if "cloned" in r]
    assert len(refines) >= 25  # every 10 steps after step 10
    for key in ("cloned", "split", "pruned", "budget_dropped"):
        assert sum(r[key] for r in refines) > 0, f"no refine step ever {key} anything"
    assert [r["step"] for r in reports if r.get("opacity_reset")] == [150]
    counts = [i["num_primitives"] for i in infos]
    assert max(counts) == BUDGET and all(n <= BUDGET for n in counts)
    assert trainer.config.train.near == pytest.approx(1e-4)


def test_outputs_written_and_finite(stressed):
    trainer, result, _ = stressed
    out = result.out_dir
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["steps"] == STEPS and metrics["num_primitives"] == result.num_primitives
    for key in ("psnr", "ssim", "final_loss"):
        assert isinstance(metrics[key], float) and math.isfinite(metrics[key]), (key, metrics[key])
    assert [h["step"] for h in metrics["history"]] == [150]
    assert all(math.isfinite(h["psnr"]) for h in metrics["history"])

    state = load_checkpoint(out / "checkpoint.pt")
    assert state["step"] == STEPS
    assert set(state["model"]["params"]) == set(trainer.model.params)
    assert not nonfinite(state["model"]["params"].items())
    assert not nonfinite(state["modules"].items())

    loaded = load_ply(out / "point_cloud.ply")
    assert loaded.num_primitives == result.num_primitives
    assert not nonfinite(loaded.params.items())


def test_surfels_survive_the_stress_config(tmp_path):
    """The 2DGS renderer and its strategy path under the same settings (shorter: past the first reset, which comes
    earlier, since a reset needs a whole reset interval of training after it)."""
    trainer, result, infos = run_stress(tmp_path, 160, **{"model.kind": "surfels", "eval.every": 0,
                                                          "strategy.reset_every": 60})
    assert isinstance(trainer.model, SurfelModel) and result.steps == 160
    assert any(i["densify"] and i["densify"].get("opacity_reset") for i in infos)
    assert not nonfinite(trainer.named_parameters())
    assert math.isfinite(result.metrics["psnr"]) and math.isfinite(result.metrics["final_loss"])


def test_stress_config_loads_and_stays_stressed():
    """The stressed keys against the built-in defaults (Config()) and configs/default.yaml."""
    stress = load_config(STRESS)
    refs = (Config(), load_config(DEFAULT))
    assert stress.data.path is None  # runs on the built-in scene with no data on disk
    assert stress.train.nan_guard
    for ref in refs:
        o, ro = stress.optim, ref.optim
        for lr in ("means_lr", "means_lr_final", "scales_lr", "quats_lr", "opacities_lr", "sh0_lr", "shN_lr"):
            assert getattr(o, lr) >= 4 * getattr(ro, lr), lr
        s, rs = stress.strategy, ref.strategy
        assert s.grad_threshold <= rs.grad_threshold / 5
        assert s.refine_start < rs.refine_start and s.refine_every <= rs.refine_every / 5
        assert stress.model.sh_interval == 0 != ref.model.sh_interval
        assert stress.model.init == "random" != ref.model.init
        assert stress.train.near <= ref.train.near / 50
    default_yaml = refs[1]
    assert stress.strategy.max_primitives >= 3 * default_yaml.strategy.max_primitives  # Config()'s is 1M
    assert stress.extensions["environment"]["lr"] >= 5 * default_yaml.extensions["environment"]["lr"]
    s = stress.strategy
    assert s.refine_stop > stress.train.steps  # densification never stops
    assert 0 < s.reset_every < stress.train.steps
    assert s.size_prune_start < stress.train.steps and s.prune_world_scale > 0 and s.prune_screen_radius > 0
    assert stress.model.sh_degree == 3
    assert stress.model.background_points > 0 and stress.model.background_radius >= 10
    # The budget must leave room over the initial points, or densification never runs.
    assert stress.strategy.max_primitives > stress.model.init_points + stress.model.background_points
