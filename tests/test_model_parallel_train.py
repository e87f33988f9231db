"""warpgs-train with train.parallel=model on two gloo processes: each rank owns half of the primitives and renders
one view of each step from both halves. The run ends where one process with the same global batch ends (Adam's
moments, densification statistics, parameters), writes the single-process checkpoint format, resumes on two
processes through a refine to the primitive count one process reaches, and on one process. The terms that read the
model (opacity, scale, count) are the whole model's on every shard."""
import dataclasses
import json
import subprocess
import sys

import pytest
import torch

from gloo_helpers import free_port, start_two_ranks
from test_distributed import LAUNCH_TIMEOUT, _env, _overrides
from warpgs.data.formats.synthetic import RigSettings, write_synthetic_scene
from warpgs.model.gaussians import GaussianModel, SurfelModel
from warpgs.train.checkpoint import load_checkpoint
from warpgs.train.distributed import Ranks
from warpgs.train.model_parallel import shard_training
from warpgs.train.optim import build_optimizer
from warpgs.train.sharded_step import check_config
from warpgs.train.strategy import DensifyStrategy, StrategyConfig
from warpgs.train.trainer import Trainer

K, STEPS = 6, 10  # no refine before K; one at step 8
# The Gestalt terms read the model: on a shard they must still be the whole model's means and counts.
SETTINGS = {"strategy.refine_start": 4, "strategy.refine_every": 4, "losses.opacity": 0.05, "losses.scale": 0.008,
            "losses.count": 0.001}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_synthetic_scene(tmp_path_factory.mktemp("mp") / "orbit32", "orbit",
                                 RigSettings(width=32, height=24, n_orbit=16), n_points=400)


def _launch(overrides, *flags):
    cmd = [sys.executable, "-m", "warpgs.cli", "train", "default", "--nproc", "2", "--quiet", *flags, *overrides,
           "train.parallel=model"]
    run = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=LAUNCH_TIMEOUT)
    assert run.returncode == 0, run.stderr[-3000:]


def _one_process(scene, out, steps):
    one = Trainer(None, overrides=_overrides(scene, out, STEPS, **SETTINGS), quiet=True)
    for _ in range(steps):
        one.train_step()
    return one


def test_two_model_parallel_processes_match_one_and_resume(scene, tmp_path):
    two = tmp_path / "two"
    _launch(_overrides(scene, two, K, **SETTINGS))
    one = _one_process(scene, tmp_path / "one", K)

    saved = load_checkpoint(two / "checkpoint.pt")
    assert saved["step"] == K and saved["config"]["train"]["parallel"] == "model"
    names = [g["name"] for g in saved["optimizer"]["param_groups"]]
    want_state = one.optimizer.state_dict()["state"]
    for i, name in enumerate(names):
        # Adam's moments hold the gradient history: the same within float round-off (the sharded blend sums
        # per-primitive gradients in another order), measured against each group's scale.
        for key in ("exp_avg", "exp_avg_sq"):
            got, want = saved["optimizer"]["state"][i][key], want_state[i][key]
            assert got.shape == want.shape, (name, key)
            assert float((got - want).abs().max()) <= 1e-3 * float(want.abs().max()), (name, key)
        # Parameters: Adam's first steps move by about lr x sign(gradient), so rows whose gradient is ~0 may step
        # apart on round-off; all but a handful agree tightly.
        got, want = saved["model"]["params"][name], one.model.params[name].detach()
        off = (got - want).abs().reshape(len(want), -1).amax(1) > 1e-5
        assert int(off.sum()) <= 0.01 * len(want), (name, int(off.sum()))
    strategy = saved["strategy"]
    assert torch.equal(strategy["count"], one.strategy.stats.count)  # the binning's visibility, returned to the owners
    torch.testing.assert_close(strategy["grad_accum"], one.strategy.stats.grad_accum, atol=1e-6, rtol=1e-4)
    for name, p in one.modules.named_parameters():  # replicated modules: gradients all-reduced
        torch.testing.assert_close(saved["modules"][name], p.detach(), atol=1e-6, rtol=1e-5)

    # Rank 0 wrote the run's files, of the gathered model.
    metrics = json.loads((two / "metrics.json").read_text())
    assert metrics["num_views"] == 2 and metrics["num_primitives"] == 400
    # Evaluated in rounds of one view per rank, each from both shards: one process's scores of its model.
    mine = one.evaluate()
    for name, scores in mine["per_view"].items():
        assert metrics["per_view"][name]["psnr"] == pytest.approx(scores["psnr"], abs=1e-3), name
    assert GaussianModel.load_ply(two / "point_cloud.ply").num_primitives == 400
    log = [json.loads(line) for line in (two / "log.jsonl").read_text().splitlines()]
    assert [(e["type"], e["step"]) for e in log] == [("train", 4), ("train", 6), ("eval", 6)]

    # Resumed on two processes (each takes its share of the saved whole) through the refine at step 8: the same
    # clone/split/prune decisions as one process, each owner for its rows.
    _launch(_overrides(scene, two, STEPS, **SETTINGS), "--resume")
    for _ in range(STEPS - K):
        one.train_step()
    resumed = load_checkpoint(two / "checkpoint.pt")
    assert resumed["step"] == STEPS
    assert len(resumed["model"]["params"]["means"]) == one.model.num_primitives > 400
    # ... and the checkpoint resumes on one process too.
    single = Trainer(None, overrides=_overrides(scene, two, STEPS + 1, **SETTINGS), quiet=True, resume=True)
    assert single.step == STEPS and single.model.num_primitives == one.model.num_primitives
    single.train_step()


def test_steps_auto_scores_the_validation_views_from_every_shard(scene, tmp_path):
    """train.steps=auto with train.parallel=model: the held-out training views are rendered in rounds from both
    shards, so the rule decides on the whole model's score: the last validation score equals one process's score of
    the saved model (no polish: the run ends at that validation)."""
    from warpgs.metrics.image import psnr

    auto = {"train.steps": "auto", "schedule.max_steps": 400, "schedule.val_every": 10, "schedule.patience": 20,
            "schedule.min_gain": 0.3, "schedule.settle": 0, "schedule.polish": 0, "schedule.val_nth": 4,
            "strategy.refine_stop": 400}
    run = tmp_path / "mp_auto"
    overrides = _overrides(scene, run, "auto", **auto)
    _launch(overrides)
    schedule = json.loads((run / "metrics.json").read_text())["schedule"]
    assert [d["decision"] for d in schedule["decisions"]] == ["stop_densifying", "stop"]  # the rule, not the bound
    assert schedule["end"] < 400 and schedule["validation"][-1]["step"] == schedule["end"]

    one = Trainer(None, overrides=overrides, quiet=True, resume=True)
    assert one.step == schedule["end"] and one.views.held_out
    views = [one.views.kept_or_new(i) for i in one.views.held_out]
    with torch.no_grad():
        mine = sum(float(psnr(one.render(v).rgb.clamp(0.0, 1.0), v.image)) for v in views) / len(views)
    assert schedule["validation"][-1]["psnr"] == pytest.approx(mine, abs=1e-3)


def test_a_shard_is_its_rows_of_model_optimizer_and_statistics_and_its_share_of_the_budget():
    torch.manual_seed(0)
    n = 7
    model = GaussianModel(torch.randn(n, 3), torch.randn(n, 3), torch.randn(n, 4), torch.randn(n),
                          torch.rand(n, 1, 3), torch.zeros(n, 3, 3))

    def stepped():  # a copy of the model after one Adam step (moments that differ row by row)
        m = GaussianModel.from_dict(model.to_dict())
        opt = build_optimizer(m)
        for p in m.params.values():
            p.grad = torch.arange(p.numel(), dtype=torch.float32).reshape(p.shape)
        opt.step()
        return m, opt

    whole, whole_opt = stepped()
    shards = []
    for rank in (0, 1):
        m, opt = stepped()
        strategy = DensifyStrategy(StrategyConfig(max_primitives=101))
        strategy.initialize(m)
        strategy.stats.count += torch.arange(n)
        rows = shard_training(m, opt, strategy, Ranks(rank, 2))
        shards.append((rows, m, opt, strategy))
    (r0, m0, o0, s0), (r1, m1, o1, s1) = shards
    assert (r0, r1) == (slice(0, 4), slice(4, 7)) and (m0.num_primitives, m1.num_primitives) == (4, 3)
    for name, p in whole.params.items():
        assert torch.equal(torch.cat([m0.params[name], m1.params[name]]), p), name
        for key in ("exp_avg", "exp_avg_sq"):
            got = torch.cat([o0.state[m0.params[name]][key], o1.state[m1.params[name]][key]])
            assert torch.equal(got, whole_opt.state[p][key]), (name, key)
    assert torch.equal(torch.cat([s0.stats.count, s1.stats.count]), torch.arange(n))
    assert (s0.config.max_primitives, s1.config.max_primitives) == (51, 50)
    with pytest.raises(ValueError, match="3D Gaussians only"):
        surfels = SurfelModel(torch.randn(n, 3), torch.randn(n, 2), torch.randn(n, 4), torch.randn(n),
                              torch.rand(n, 1, 3), torch.zeros(n, 3, 3))
        shard_training(surfels, build_optimizer(surfels), DensifyStrategy(), Ranks(0, 2))


def test_model_parallel_settings_are_checked_before_anything_is_built():
    from warpgs.cli.commands import resolve_config_source
    from warpgs.config.loader import load_config

    def config(*overrides):
        return load_config(resolve_config_source("default"), list(overrides))

    check_config(config("train.batch_size=4"), 2)
    with pytest.raises(ValueError, match="train.batch_size: 3 is not a multiple of the 2 processes"):
        check_config(config("train.batch_size=3"), 2)
    with pytest.raises(ValueError, match="train.max_sigmas"):
        check_config(config("train.batch_size=2", "train.max_sigmas=3.0"), 2)
    with pytest.raises(ValueError, match="train.viewer"):
        check_config(config("train.batch_size=2", "train.viewer=true"), 2)
    with pytest.raises(ValueError, match="3D Gaussians only"):
        check_config(config("train.batch_size=2", "model.kind=surfels"), 2)


def test_evaluation_rounds_give_every_rank_the_same_number_of_renders_in_turn():
    from types import SimpleNamespace

    from warpgs.train.evaluation import _Rounds

    views = [SimpleNamespace(name=f"v{i}") for i in range(5)]
    for rank, want in ((0, [["v0", "v3"], ["v1", "v4"], ["v2", "v0"]]), (1, [["v0", "v3"], ["v1", "v4"], ["v2", "v0"]])):
        calls = []
        rounds = _Rounds(lambda cams: calls.append([c.name for c in cams]) or cams[rank].name, Ranks(rank, 2), views)
        mine = views[Ranks(rank, 2).shard(5)]
        got = [rounds.next(v) for v in mine]
        rounds.finish()
        assert got == [v.name for v in mine] and calls == want  # rank 1's share is used up: v0 stands in
        with pytest.raises(RuntimeError, match="out of turn"):
            _Rounds(lambda cams: None, Ranks(rank, 2), views).next(views[4])


def test_a_share_built_in_cpu_memory_moves_to_its_device_with_its_optimizer_state():
    # A model-parallel run builds the whole model in CPU memory and moves only its share to the GPU; "meta" stands
    # in for the GPU here (the move is the same call).
    from warpgs.train.model_parallel import move_training

    n = 6
    model = GaussianModel(torch.randn(n, 3), torch.randn(n, 3), torch.randn(n, 4), torch.randn(n),
                          torch.rand(n, 1, 3), torch.zeros(n, 3, 3))
    opt = build_optimizer(model)
    for p in model.params.values():
        p.grad = torch.ones_like(p)
    opt.step()
    strategy = DensifyStrategy()
    strategy.initialize(model)
    move_training(model, opt, strategy, "meta")
    for group in opt.param_groups:
        (p,) = group["params"]
        assert p is model.params[group["name"]] and p.device.type == "meta"
        state = opt.state[p]
        assert state["exp_avg"].device.type == "meta" and state["exp_avg_sq"].device.type == "meta"
        assert state["step"].device.type == "cpu"  # Adam keeps its step count on the CPU
    assert {getattr(strategy.stats, k).device.type for k in ("grad_accum", "count", "max_radii", "max_screen")} == {"meta"}
    assert not any(g["fused"] for g in opt.param_groups)  # "auto" off the GPU: foreach, as built
    # optim.adam_kernel=fused (what "auto" means on a GPU): the fused kernel, its step count on the device.
    move_training(model, opt, strategy, "meta", adam_kernel="fused")
    assert all(g["fused"] and not g["foreach"] for g in opt.param_groups) and opt.defaults["fused"]
    assert {st["step"].device.type for st in opt.state.values()} == {"meta"}


NAN_LOSS = '''
import torch.distributed as dist
from warpgs.losses.registry import register_loss

@register_loss("test_nan_on_rank1", outputs=(), weight=1.0, overwrite=True)
def nan_on_rank1(render_out, batch, model, step):
    """A finite value (0) whose gradient is NaN on rank 1's rows only, at step 2: d sqrt(|x|) at x = 0."""
    zero = (model.means[:1, 0] * 0.0).sum()
    bad = step == 2 and dist.is_initialized() and dist.get_rank() == 1
    return zero.abs().sqrt() if bad else zero
'''


def test_non_finite_gradients_on_one_rank_stop_both_at_that_step(scene, tmp_path):
    # With train.parallel=model each rank checks only its own rows: the other rank learns of it through the step's
    # all-reduce and stops too (exit 3) instead of waiting in the next collective. Ranks started directly (no
    # torchrun agent that would stop the survivor for it).
    loss = tmp_path / "nan_loss.py"
    loss.write_text(NAN_LOSS)
    overrides = _overrides(scene, tmp_path / "run", K, **SETTINGS, **{"imports": f"[{loss}]",
                                                                       "losses.test_nan_on_rank1": 1.0})
    results = start_two_ranks([sys.executable, "-m", "warpgs.cli", "train", "default", *overrides, "train.parallel=model"],
                              _env(WORLD_SIZE=2, MASTER_ADDR="127.0.0.1", MASTER_PORT=free_port()), LAUNCH_TIMEOUT)
    for rank, (code, _, err) in enumerate(results):
        assert code == 3, f"rank {rank}: {err[-2000:]}"  # EXIT_NONFINITE
    err0 = results[0][2]
    assert "step 2" in err0 and "another rank's gradients are not finite" in err0
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


NO_GATHER = '''
import warpgs.train.trainer as trainer

def refuse(*args, **kwargs):
    raise AssertionError("the whole training state was gathered to save a checkpoint")

trainer.gathered_training = refuse
'''


def test_sharded_checkpoints_gather_nothing_and_the_single_file_is_written_on_request(scene, tmp_path):
    from warpgs.train.sharded_checkpoint import shard_folder

    run = tmp_path / "run"
    refuse = tmp_path / "no_gather.py"
    refuse.write_text(NO_GATHER)
    # Checkpoints at steps 2 and 4, each rank its own share: nothing may gather the whole training state.
    _launch(_overrides(scene, run, 4, **SETTINGS, **{"imports": f"[{refuse}]", "train.checkpoint_every": 2}))
    index = torch.load(run / "checkpoint.pt", weights_only=True)
    assert index["step"] == 4 and index["version"] == 3 and "model" not in index
    assert index["shards"]["files"] == ["checkpoint-shards/step-00000004/rank-0-of-2.pt",
                                        "checkpoint-shards/step-00000004/rank-1-of-2.pt"]
    assert index["shards"]["rows"] == [200, 200]
    assert [p.name for p in shard_folder(run / "checkpoint.pt").iterdir()] == ["step-00000004"]  # step 2's: gone
    for name, rows in zip(index["shards"]["files"], index["shards"]["rows"]):
        shard = load_checkpoint(run / name)
        assert shard["model"]["params"]["means"].shape[0] == rows and shard["step"] == 4
    whole = load_checkpoint(run / "checkpoint.pt")  # put together: the single-file layout
    assert whole["model"]["params"]["means"].shape[0] == 400 and whole["strategy"]["count"].shape == (400,)

    # Resumed from the shards on two processes, saving one file on request: the shards make way for it.
    _launch(_overrides(scene, run, 6, **SETTINGS, **{"output.checkpoint_shards": "false", "imports": "[]"}),
            "--resume")
    single = torch.load(run / "checkpoint.pt", weights_only=True)
    assert single["step"] == 6 and single["version"] == 2 and "shards" not in single
    assert single["model"]["params"]["means"].shape[0] == len(single["strategy"]["count"]) >= 400
    assert not shard_folder(run / "checkpoint.pt").exists()


def test_a_missing_shard_is_named(tmp_path):
    from warpgs.train.checkpoint import save_checkpoint
    from warpgs.train.sharded_checkpoint import index_state

    save_checkpoint(tmp_path / "checkpoint.pt", index_state(tmp_path / "checkpoint.pt", 7, [3, 4]))
    with pytest.raises(FileNotFoundError, match=r"rank-0-of-2.pt of rank 0 is missing .*shared storage"):
        load_checkpoint(tmp_path / "checkpoint.pt")


class _TwoRanks:
    """Rank `rank` of two in one process: what Checkpointer.save_sharded asks of Ranks, with the answers the two
    ranks would give (every share finite, `rows` rows each)."""

    def __init__(self, rank, rows):
        self.rank, self.world_size, self.rows = rank, 2, rows
        self.is_main = rank == 0

    def all_gather_object(self, obj, what=""):
        return list(self.rows) if isinstance(obj, int) else [obj, obj]


def test_shards_put_together_are_the_single_file_checkpoint(scene, tmp_path):
    import copy

    from warpgs.train.state import Checkpointer

    tr = Trainer(None, overrides=_overrides(scene, tmp_path / "one", K, **SETTINGS), quiet=True)
    for _ in range(5):  # through the refine at step 4: moments of new rows are zero, the rest are not
        tr.train_step()
    whole = tr.state_dict()
    n = tr.model.num_primitives
    rows = [Ranks(r, 2).shard(n) for r in (0, 1)]
    path = tmp_path / "sharded" / "checkpoint.pt"
    for rank in (1, 0):  # rank 0 writes the index last, after every shard
        model = GaussianModel.from_dict(tr.model.to_dict())
        optimizer = build_optimizer(model)
        optimizer.load_state_dict(tr.optimizer.state_dict())
        strategy = copy.copy(tr.strategy)
        shard_training(model, optimizer, strategy, Ranks(rank, 2))
        parts = dataclasses.replace(tr.training_state(), model=model, optimizer=optimizer, strategy=strategy)
        Checkpointer(path, "cpu", guard=tr.guard).save_sharded(parts, _TwoRanks(rank, [len(range(n)[s]) for s in rows]))
    got = load_checkpoint(path)
    for name, t in whole["model"]["params"].items():
        assert torch.equal(got["model"]["params"][name], t), name
    for i, st in whole["optimizer"]["state"].items():
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(got["optimizer"]["state"][i][key], st[key]), (i, key)
    for key in ("grad_accum", "count", "max_radii", "max_screen"):
        assert torch.equal(got["strategy"][key], whole["strategy"][key]), key
    assert got["step"] == whole["step"] == 5 and got["optimizer"]["param_groups"] == whole["optimizer"]["param_groups"]
