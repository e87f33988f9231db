"""Data-parallel training on the CPU (gloo): two processes with one view each end where one process with a batch
of two ends, through a densification refine; a checkpoint of the two resumes on one; only rank 0 writes the run's
files; a rank that dies makes the other stop with an error naming the failed collective instead of hanging."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from gloo_helpers import free_port, start_two_ranks
from warpgs.data.formats.synthetic import RigSettings, write_synthetic_scene
from warpgs.train.checkpoint import load_checkpoint
from warpgs.train.distributed import Ranks
from warpgs.train.trainer import Trainer

ROOT = Path(__file__).resolve().parent.parent
LAUNCH_TIMEOUT = 120  # s: bounds every subprocess run, so a hang fails the test instead of stalling CI
K, STEPS = 8, 12  # the two-process run stops at K (refines at 3 and 6); one process goes on to STEPS (refine at 9)

DIE_EXTENSION = '''
import os
import torch.distributed as dist
from warpgs.train.extensions import Extension, register_extension

@register_extension("test_die", overwrite=True)
class Die(Extension):
    """Rank `rank` leaves at the end of step `step`: os._exit (no clean-up at all) or an exception."""
    def __init__(self, step=3, rank=1, how="exit"):
        self.step, self.rank, self.how = int(step), int(rank), how

    def after_step(self, trainer, step, info):
        if step == self.step and dist.is_initialized() and dist.get_rank() == self.rank:
            if self.how == "exit":
                os._exit(17)
            raise RuntimeError("test_die: failing on purpose")
'''


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """16 views at 32x24 (14 train, 2 test), 400 points: small enough for several processes on 2 cores."""
    return write_synthetic_scene(tmp_path_factory.mktemp("dist") / "orbit32", "orbit",
                                 RigSettings(width=32, height=24, n_orbit=16), n_points=400)


def _overrides(scene, out, steps, **extra):
    settings = {
        "data.path": str(scene), "output.dir": str(out), "train.steps": steps, "train.device": "cpu",
        "train.batch_size": 2, "train.progress": False, "train.checkpoint_every": 0, "train.log_every": 4,
        "eval.every": 0, "eval.lpips": False, "model.sh_interval": 4,
        # A constant position lr: the first K steps do not depend on train.steps, so runs of K and STEPS agree.
        "optim.means_lr_final": 1.6e-4,
        "strategy.refine_start": 2, "strategy.refine_every": 3, "strategy.refine_stop": 1000,
        "strategy.reset_every": 0, "strategy.max_primitives": 4000, "extensions.environment.degree": 2,
        "train.dist_timeout": 60,
    }
    settings.update(extra)
    return [f"{k}={v}" for k, v in settings.items()]


def _env(**extra) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
               OMP_NUM_THREADS="1")
    env.update({k: str(v) for k, v in extra.items()})
    return env


def _snapshot(tr) -> dict:
    out = {f"param.{n}": p.detach().clone() for n, p in tr.named_parameters()}
    out.update({f"strategy.{k}": getattr(tr.strategy.stats, k).clone() for k in ("grad_accum", "count", "max_radii")})
    return out


def _assert_close(got: dict, want: dict, what: str) -> None:
    assert got.keys() == want.keys(), what
    for key in want:
        assert got[key].shape == want[key].shape, f"{what}: {key} {list(got[key].shape)} != {list(want[key].shape)}"
        assert torch.allclose(got[key].float(), want[key].float(), rtol=1e-5, atol=1e-7), f"{what}: {key}"


def test_two_processes_match_one_with_the_same_batch_and_resume_on_one(scene, tmp_path):
    # Two gloo processes, one view each, launched as `warpgs-train --nproc 2` (torch.distributed.run).
    two = tmp_path / "two"
    cmd = [sys.executable, "-m", "warpgs.cli", "train", "default", "--nproc", "2", *_overrides(scene, two, K)]
    run = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=LAUNCH_TIMEOUT)
    assert run.returncode == 0, run.stderr[-3000:]

    # One process, the same global batch of two views.
    one = Trainer(None, overrides=_overrides(scene, tmp_path / "one", STEPS), quiet=True)
    refines = [one.train_step()["densify"] for _ in range(K)]
    assert sum(r is not None for r in refines) == 2 and one.model.num_primitives > 400

    saved = load_checkpoint(two / "checkpoint.pt")
    assert saved["step"] == K
    got = {f"param.{n}": t for n, t in saved["model"]["params"].items()}
    got.update({f"param.modules.{n}": t for n, t in saved["modules"].items()})
    got.update({f"strategy.{k}": saved["strategy"][k] for k in ("grad_accum", "count", "max_radii")})
    _assert_close(got, _snapshot(one), "two processes vs one at step 8")

    # Rank 0 alone wrote the run's files: one log entry per logged step, metrics over both test views
    # (evaluated one per rank and gathered) equal to one process's evaluation of the same model.
    log = [json.loads(line) for line in (two / "log.jsonl").read_text().splitlines()]
    assert [(e["type"], e["step"]) for e in log] == [("train", 4), ("train", 8), ("eval", 8)]
    metrics = json.loads((two / "metrics.json").read_text())
    mine = one.evaluate()
    assert metrics["num_views"] == 2 and sorted(metrics["per_view"]) == sorted(mine["per_view"])
    assert metrics["psnr"] == pytest.approx(mine["psnr"], abs=1e-3)
    assert sorted(p.name for p in (two / "renders" / "test").glob("*.png")) == ["orbit_000.png", "orbit_008.png"]
    assert not list(two.glob(".*.tmp"))

    # The two-process checkpoint resumes on one process (no per-rank state in it) and ends where one process
    # that ran all the way ends, through another refine.
    for _ in range(STEPS - K):
        one.train_step()
    resumed = Trainer(None, overrides=_overrides(scene, two, STEPS), quiet=True, resume=True)
    assert resumed.step == K
    for _ in range(STEPS - K):
        resumed.train_step()
    _assert_close(_snapshot(resumed), _snapshot(one), "resumed on one process vs one process at step 12")


def test_steps_auto_decides_on_two_processes_as_on_one(scene, tmp_path):
    """train.steps=auto (the gaussians preset's default) under torchrun: the validation views are scored across
    ranks and every rank takes rank 0's decision, so two processes with one view each stop densifying and stop
    training at the steps one process with a batch of two does, and end at the same model."""
    auto = {"train.steps": "auto", "schedule.max_steps": 400, "schedule.val_every": 10, "schedule.patience": 20,
            "schedule.min_gain": 0.3, "schedule.settle": 0, "schedule.polish": 10, "schedule.val_nth": 4,
            "strategy.refine_stop": 400}
    runs = {}
    for name, nproc in (("two", ["--nproc", "2"]), ("one", [])):
        cmd = [sys.executable, "-m", "warpgs.cli", "train", "default", *nproc,
               *_overrides(scene, tmp_path / name, "auto", **auto)]
        run = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=LAUNCH_TIMEOUT)
        assert run.returncode == 0, run.stderr[-3000:]
        runs[name] = json.loads((tmp_path / name / "metrics.json").read_text())["schedule"]
    one, two = runs["one"], runs["two"]
    # Decided by the rule, not by the bound: densification stopped, then training, before schedule.max_steps.
    assert [d["decision"] for d in one["decisions"]] == ["stop_densifying", "stop"]
    assert one["end"] < 400
    for key in ("densify_stop", "polish_start", "end", "best_step"):
        assert two[key] == one[key], key
    assert [v["step"] for v in two["validation"]] == [v["step"] for v in one["validation"]]
    assert [v["psnr"] for v in two["validation"]] == pytest.approx([v["psnr"] for v in one["validation"]], abs=1e-3)
    a, b = load_checkpoint(tmp_path / "two" / "checkpoint.pt"), load_checkpoint(tmp_path / "one" / "checkpoint.pt")
    assert a["step"] == b["step"] == one["end"]
    _assert_close(a["model"]["params"], b["model"]["params"], "two processes vs one, steps=auto")


def test_a_rank_that_dies_stops_the_other_with_a_clear_error(scene, tmp_path, how="exit"):
    # The two ranks are started directly (torchrun's environment, no torchrun agent to kill the survivor), so
    # what is tested is the survivor's own detection: its next collective fails and it exits with a message.
    # how="exit" is a crash (os._exit: no clean-up, as a segfault or the OOM killer); how="raise" (a Python error
    # on one rank) behaves the same and was checked too, but costs another two process start-ups on CI's 2 cores.
    ext = tmp_path / "die_ext.py"
    ext.write_text(DIE_EXTENSION)
    overrides = _overrides(scene, tmp_path / "run", 40, **{"imports": f"[{ext}]", "extensions.test_die.step": 3,
                                                            "extensions.test_die.how": how})
    (code0, _, err0), (code1, _, err1) = start_two_ranks(
        [sys.executable, "-m", "warpgs.cli", "train", "default", *overrides],
        _env(WORLD_SIZE=2, MASTER_ADDR="127.0.0.1", MASTER_PORT=free_port()), LAUNCH_TIMEOUT)
    assert code1 == (17 if how == "exit" else 1), err1[-2000:]
    if how == "raise":
        assert "test_die: failing on purpose" in err1
    assert code0 == 4, err0[-2000:]  # EXIT_DISTRIBUTED
    assert "rank 0 of 2:" in err0 and "step 4" in err0 and "failed: another rank stopped" in err0, err0[-2000:]
    assert not (tmp_path / "run" / "checkpoint.pt").exists()  # nothing half-written; none was due


def test_ranks_share_out_batches_and_derive_their_own_seeds():
    for n in (2, 3, 7, 8):
        for world in (1, 2, 3):
            slices = [Ranks(r, world).shard(n) for r in range(world)]
            items = [i for s in slices for i in range(n)[s]]
            assert items == list(range(n))  # disjoint, in order, covering the batch
            sizes = [len(range(n)[s]) for s in slices]
            assert max(sizes) - min(sizes) <= 1
    seeds = {Ranks(r, 4).derived_seed(0, 0) for r in range(4)}
    assert len(seeds) == 4 and Ranks(1, 4).derived_seed(0, 0) == Ranks(1, 4).derived_seed(0, 0)
    assert Ranks(1, 4).derived_seed(0, 0) != Ranks(1, 4).derived_seed(0, 100)


def test_a_batch_smaller_than_the_world_is_refused_by_name(scene, tmp_path, monkeypatch):
    import warpgs.train.trainer_build as trainer_build

    monkeypatch.setattr(trainer_build, "setup_ranks", lambda device, **kw: (Ranks(0, 4), device))
    with pytest.raises(ValueError, match=r"train.batch_size: 2 is less than the 4 processes"):
        Trainer(None, overrides=_overrides(scene, tmp_path / "x", 2), quiet=True)


def test_nproc_builds_the_torchrun_command():
    from warpgs.cli.launch import torchrun_args

    args = torchrun_args(2, ["gaussians", "--nproc", "2", "--out", "o", "--nproc=3", "steps=5"])
    assert args == ["--standalone", "--nproc_per_node=2", "-m", "warpgs.cli", "train", "gaussians", "--out", "o",
                    "steps=5"]
