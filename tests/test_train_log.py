"""Training logs: log.jsonl (every logged step and every evaluation, trimmed on resume), TensorBoard scalars and
evaluation images with train.log=tensorboard, and the error when the tensorboard package is missing."""
import json
import sys

import pytest
import torch

from train_fixtures import quick_overrides
from warpgs.config.loader import ConfigError, load_config
from warpgs.train.log import LOG_FILE, TENSORBOARD_DIR, MissingExtraError, TrainLog
from warpgs.train.trainer import Trainer

STEPS = 40
LOGGED = {"train.log_every": 10, "eval.every": 20}


def _entries(out_dir, kind=None):
    lines = (out_dir / LOG_FILE).read_text().splitlines()
    entries = [json.loads(line) for line in lines]
    return [e for e in entries if kind is None or e["type"] == kind]


def _run(out_dir, **extra):
    infos = {}
    trainer = Trainer(None, overrides=quick_overrides(out_dir, STEPS, **LOGGED, **extra),
                      callbacks=[lambda tr, step, info: infos.__setitem__(step + 1, info)], quiet=True)
    return trainer, trainer.fit(), infos


@pytest.fixture(scope="module")
def jsonl_run(tmp_path_factory):
    return _run(tmp_path_factory.mktemp("jsonl"))


def test_jsonl_has_every_logged_step_with_the_values_of_that_step(jsonl_run):
    trainer, result, infos = jsonl_run
    train = _entries(result.out_dir, "train")
    assert [e["step"] for e in train] == [10, 20, 30, 40]
    for e in train:
        info = infos[e["step"]]
        assert e["loss"] == info["loss"] and e["losses"] == info["values"] and e["psnr"] == info["psnr"]
        assert e["num_primitives"] == info["num_primitives"]
        assert set(e["losses"]) == {"l1", "dssim"}
        assert set(e["lr"]) >= {"means", "quats", "log_scales", "logit_opacities", "sh0", "shN"}
        assert e["elapsed"] >= e["train_seconds"] > 0
    assert train[-1]["lr"]["means"] < train[0]["lr"]["means"]  # the position lr decays: read live, not once
    assert [e["train_seconds"] for e in train] == sorted(e["train_seconds"] for e in train)


def test_jsonl_has_the_periodic_and_final_evaluations(jsonl_run):
    trainer, result, _ = jsonl_run
    evals = _entries(result.out_dir, "eval")
    assert [(e["step"], e["final"]) for e in evals] == [(20, False), (STEPS, True)]
    assert evals[0]["psnr"] == result.history[0]["psnr"] and evals[0]["split"] == "test"
    assert evals[1]["psnr"] == result.metrics["psnr"] and evals[1]["num_views"] == 2
    assert evals[1]["num_primitives"] == result.num_primitives


def test_resume_keeps_the_log_up_to_the_checkpoint(tmp_path):
    first = Trainer(None, overrides=quick_overrides(tmp_path, 20, **LOGGED), quiet=True)
    first.fit()
    with open(tmp_path / LOG_FILE, "a") as f:  # as if a killed run had logged past its checkpoint
        f.write(json.dumps({"type": "train", "step": 30}) + "\n" + '{"type": "tr')
    resumed = Trainer(None, overrides=quick_overrides(tmp_path, STEPS, **LOGGED), resume=True, quiet=True)
    resumed.fit()
    assert [e["step"] for e in _entries(tmp_path, "train")] == [10, 20, 30, 40]
    assert [(e["step"], e["final"]) for e in _entries(tmp_path, "eval")] == [(20, True), (40, True)]


def test_log_unit_cadence_nonfinite_values_and_off(tmp_path):
    log = TrainLog(tmp_path, every=10)
    assert [s for s in range(1, 26) if log.due(s, 25)] == [10, 20, 25]
    with log.open(0):
        log.train(10, {"loss": float("nan"), "values": {"l1": float("inf")}, "psnr": None, "num_primitives": 3},
                  {"means": 1e-4}, 0.5)
    (entry,) = _entries(tmp_path)
    assert entry["loss"] is None and entry["losses"] == {"l1": None} and entry["lr"] == {"means": 1e-4}
    with TrainLog(tmp_path / "off", kind="none").open(0) as off:
        off.train(10, {"loss": 1.0, "values": {}, "psnr": None, "num_primitives": 3}, {}, 0.5)
    assert not (tmp_path / "off").exists()
    with pytest.raises(ValueError, match="train.log: expected one of"):
        TrainLog(tmp_path, kind="csv")


def test_config_checks_the_log_kind():
    assert load_config(None, ["train.log=tensorboard"]).train.log == "tensorboard"
    with pytest.raises(ConfigError, match=r"train\.log: expected one of .*did you mean 'tensorboard'"):
        load_config(None, ["train.log=tensorbord"])


def test_missing_tensorboard_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "tensorboard", None)  # makes `import tensorboard` fail
    monkeypatch.delitem(sys.modules, "torch.utils.tensorboard", raising=False)
    with pytest.raises(MissingExtraError, match=r"train\.log: 'tensorboard' needs .*warpgs\[tensorboard\]") as e:
        Trainer(None, overrides=quick_overrides(tmp_path, 5, **{"train.log": "tensorboard"}), quiet=True)
    assert isinstance(e.value, ImportError) and isinstance(e.value, ValueError)  # the CLI reports ValueErrors
    assert not (tmp_path / "checkpoint.pt").exists()
    TrainLog(tmp_path, kind="jsonl")  # the default needs no extra


def test_tensorboard_scalars_and_images_match_the_jsonl_and_leave_training_alone(tmp_path, jsonl_run):
    pytest.importorskip("tensorboard", reason="the tensorboard package is not installed (pip install "
                                              "'warpgs[tensorboard]'); the test extra installs it")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    trainer, result, _ = _run(tmp_path, **{"train.log": "tensorboard"})
    ref_trainer, ref_result, _ = jsonl_run
    for name, p in trainer.model.params.items():
        assert torch.equal(p, ref_trainer.model.params[name]), name
    assert _entries(tmp_path, "train")[-1]["loss"] == _entries(ref_result.out_dir, "train")[-1]["loss"]

    events = EventAccumulator(str(tmp_path / TENSORBOARD_DIR), size_guidance={"images": 0, "scalars": 0})
    events.Reload()
    tags = events.Tags()
    train = _entries(tmp_path, "train")
    loss = events.Scalars("train/loss")
    assert [s.step for s in loss] == [e["step"] for e in train]
    assert [s.value for s in loss] == pytest.approx([e["loss"] for e in train], rel=1e-6)
    assert {"loss/l1", "loss/dssim", "lr/means", "train/psnr", "train/num_primitives"} <= set(tags["scalars"])
    evals = _entries(tmp_path, "eval")
    psnr = events.Scalars("eval/psnr")
    assert [s.step for s in psnr] == [e["step"] for e in evals] == [20, STEPS]
    assert [s.value for s in psnr] == pytest.approx([e["psnr"] for e in evals], rel=1e-6)
    assert sorted(tags["images"]) == ["eval/orbit_000", "eval/orbit_008"]
    image = events.Images("eval/orbit_000")
    assert [i.step for i in image] == [20, STEPS] and (image[0].width, image[0].height) == (64, 48)
