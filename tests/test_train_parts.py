"""The trainer's collaborators, each built alone from its explicit dependencies (no Trainer, no rendering):
NonFiniteGuard, TrainViews, LossSet, Evaluator, Checkpointer and the loop's RunningMean."""
import math
from collections import Counter
from types import SimpleNamespace

import pytest
import torch
from torch import nn

from warpgs.config.loader import Config
from warpgs.config.schema import EvalConfig
from warpgs.losses import LossResult, register_loss, unregister_loss
from warpgs.model.gaussians import GaussianModel
from warpgs.train.evaluation import Evaluator
from warpgs.train.guard import NonFiniteError, NonFiniteGuard, StepGuard
from warpgs.train.loop import RunningMean
from warpgs.train.loss_set import LossSet, resolve_terms
from warpgs.train.optim import build_optimizer
from warpgs.train.state import Checkpointer, RunCounters, TrainingState
from warpgs.train.strategy import DensifyStrategy, StrategyConfig
from warpgs.train.views import TrainViews

# The keys of checkpoints written by every trainer so far, in order: old checkpoints must keep loading.
CHECKPOINT_KEYS = ["format", "version", "step", "model", "optimizer", "module_optimizer", "modules", "strategy",
                   "extensions", "rng", "view_generator", "view_queue", "train_seconds", "history", "last_loss",
                   "config", "best_state"]


class FakeScene:
    """Views 0..n-1 with 4x5 images in [0.2, 0.8]; counts how often each view is loaded."""

    def __init__(self, n=6, test=(4, 5)):
        self.test = list(test)
        self.train = [i for i in range(n) if i not in self.test]
        gen = torch.Generator().manual_seed(3)
        self.images = 0.2 + 0.6 * torch.rand(n, 4, 5, 3, generator=gen)
        self.loads = Counter()

    def view(self, index, device):
        self.loads[index] += 1
        return SimpleNamespace(index=index, name=f"v{index:02d}.png", image=self.images[index].to(device))


# ----- NonFiniteGuard -----------------------------------------------------------------------------------------
def test_guard_names_the_first_nonfinite_parameter_gradient_or_loss_term():
    params = {"a": torch.zeros(3, requires_grad=True), "b": torch.ones(2, requires_grad=True)}
    guard = NonFiniteGuard(lambda: params.items())
    guard.check(0)  # all finite, no gradients yet

    params["b"].grad = torch.tensor([0.0, float("inf")])
    with pytest.raises(NonFiniteError, match=r"step 4: gradient of 'b' is not finite") as e:
        guard.check(4)
    assert (e.value.step, e.value.name) == (4, "b")

    params["b"].grad = None
    result = LossResult(torch.tensor(float("nan")), {"l1": torch.tensor(0.5), "depth": torch.tensor(float("nan"))},
                        {"l1": 1.0, "depth": 1.0})
    with pytest.raises(NonFiniteError, match="loss depth is not finite") as e:
        guard.check(5, result)
    assert e.value.name == "depth"

    params["c"] = torch.tensor([1.0, float("nan")])  # added after the guard was built: still seen
    with pytest.raises(NonFiniteError, match="parameter 'c'"):
        guard.check(6)


def test_deferred_check_skips_fused_adam_and_raises_for_its_step_at_the_next_check():
    w = torch.nn.Parameter(torch.ones(3))
    opt = torch.optim.Adam([w], lr=0.1, fused=True)
    step_guard = StepGuard(NonFiniteGuard(lambda: [("w", w)]))
    ok = LossResult(torch.tensor(1.0), {"l1": torch.tensor(1.0)}, {"l1": 1.0})
    w.grad = torch.ones(3)
    step_guard.before_optimizers(0, ok, [opt], defer=True)
    opt.step()
    step_guard.after_optimizers([opt])
    assert not hasattr(opt, "found_inf") and torch.allclose(w.detach(), torch.full((3,), 0.9))
    kept = w.detach().clone()
    w.grad = torch.tensor([1.0, float("nan"), 1.0])
    step_guard.before_optimizers(1, ok, [opt], defer=True)  # no error yet: read at the next check
    opt.step()
    step_guard.after_optimizers([opt])
    assert torch.equal(w.detach(), kept)  # the fused kernel skipped the update on its own
    assert opt.state[w]["step"].item() == 1  # and did not count the step
    w.grad = torch.ones(3)
    with pytest.raises(NonFiniteError, match=r"step 1: gradient of 'w' is not finite"):
        step_guard.before_optimizers(2, ok, [opt], defer=True)


def test_deferred_check_names_a_loss_term_and_checks_at_once_without_fused_adam():
    w = torch.nn.Parameter(torch.ones(2))
    w.grad = torch.ones(2)
    step_guard = StepGuard(NonFiniteGuard(lambda: [("w", w)]))
    bad = LossResult(torch.tensor(float("nan")), {"depth": torch.tensor(float("nan"))}, {"depth": 1.0})
    step_guard.before_optimizers(4, bad, [torch.optim.Adam([w], fused=True)], defer=True)
    with pytest.raises(NonFiniteError, match="step 4: loss depth is not finite"):
        step_guard.settle()
    step_guard.settle()  # read once: nothing pending now
    with pytest.raises(NonFiniteError, match="step 5: loss depth"):  # foreach Adam cannot skip a step: at once
        step_guard.before_optimizers(5, bad, [torch.optim.Adam([w], foreach=True)], defer=True)


def test_guard_ignores_a_sum_that_overflows_on_finite_values():
    huge = torch.full((4,), 3e38)  # each finite; their float32 sum is inf
    assert not torch.isfinite(huge.sum())
    NonFiniteGuard(lambda: [("huge", huge)]).check(0)


def test_guard_needs_a_callable():
    with pytest.raises(ValueError, match="named_parameters"):
        NonFiniteGuard({"a": torch.zeros(1)})


# ----- TrainViews ---------------------------------------------------------------------------------------------
def _draw(views, n):
    return [views.next().index for _ in range(n)]


def test_views_draw_every_training_view_once_per_epoch_in_a_seeded_order():
    scene = FakeScene(n=8, test=(7,))
    views = TrainViews(scene, "cpu", seed=5)
    drawn = _draw(views, 3 * 7)
    epochs = [drawn[i:i + 7] for i in range(0, 21, 7)]
    assert all(sorted(e) == scene.train for e in epochs)
    assert len({tuple(e) for e in epochs}) > 1  # reshuffled
    assert _draw(TrainViews(scene, "cpu", seed=5), 21) == drawn
    assert _draw(TrainViews(scene, "cpu", seed=6), 21) != drawn


def test_views_state_resumes_the_same_draws():
    scene = FakeScene(n=8, test=(7,))
    views = TrainViews(scene, "cpu", seed=1)
    _draw(views, 10)  # mid-epoch
    state = views.state_dict()
    assert set(state) == {"view_generator", "view_queue"}
    expected = _draw(views, 12)
    resumed = TrainViews(scene, "cpu", seed=99)
    resumed.load_state_dict(state)
    assert _draw(resumed, 12) == expected


def test_views_keep_device_copies_only_when_preloading():
    scene = FakeScene()
    kept = TrainViews(scene, "cpu", seed=0, preload=True)
    assert kept.view(1) is kept.view(1) and scene.loads[1] == 1
    assert kept.kept_or_new(1) is kept.view(1)
    kept.kept_or_new(4), kept.kept_or_new(4)  # evaluation views are not kept
    assert scene.loads[4] == 2
    fresh = TrainViews(scene, "cpu", seed=0, preload=False)
    fresh.view(2), fresh.view(2)
    assert scene.loads[2] == 2


def test_views_load_all_keeps_every_training_view_once_and_nothing_without_preload():
    scene = FakeScene(n=8, test=(7,))
    views = TrainViews(scene, "cpu", seed=0, preload=True)
    views.view(3)  # drawn already: not loaded again
    assert views.load_all() == 6
    assert sorted(scene.loads) == scene.train and set(scene.loads.values()) == {1}
    assert views.load_all() == 0
    _draw(views, 14)  # two epochs draw only kept copies
    assert set(scene.loads.values()) == {1}
    lazy_scene = FakeScene()
    assert TrainViews(lazy_scene, "cpu", seed=0, preload=False).load_all() == 0 and not lazy_scene.loads


def test_views_load_all_in_threads_equals_one_by_one_and_names_a_bad_image(tmp_path):
    """load_all decodes views in threads: the same tensors as loading them one by one, and a truncated image
    stops it with the file's name."""
    from data_fixtures import copy_of
    from warpgs.data import load_scene
    from warpgs.data.errors import SceneError

    root = copy_of("orbit", tmp_path / "scene")
    threaded = TrainViews(load_scene(root, split="llff"), "cpu", seed=0)
    assert threaded.load_all() == len(threaded.scene.train) > 2
    one_by_one = load_scene(root, split="llff")
    for i in one_by_one.train:
        assert torch.equal(threaded.view(i).image, one_by_one.view(i).image)
    scene = load_scene(root, split="llff")
    bad = scene.files[scene.train[3]].image
    bad.write_bytes(bad.read_bytes()[:200])
    with pytest.raises(SceneError, match=bad.name):
        TrainViews(scene, "cpu", seed=0).load_all()


def test_kept_8bit_images_take_a_quarter_of_the_memory_and_come_back_bit_for_bit(tmp_path):
    """Images from 8-bit files are kept as their codes and expanded to exactly the loaded float image; an image
    with other values (FakeScene's random floats) is kept as it is."""
    from data_fixtures import copy_of
    from warpgs.data import load_scene

    root = copy_of("orbit", tmp_path / "scene")
    views = TrainViews(load_scene(root, split="llff"), "cpu", seed=0)
    views.load_all()
    fresh = load_scene(root, split="llff")
    pixels = sum(fresh.view(i).image.numel() for i in fresh.train)
    assert views.kept_bytes() == pixels  # one byte a value, not four
    for i in fresh.train:
        drawn = views.view(i).image
        assert drawn.dtype == torch.float32 and torch.equal(drawn, fresh.view(i).image)
    floats = TrainViews(FakeScene(), "cpu", seed=0)
    floats.load_all()
    assert floats.kept_bytes() == 4 * sum(floats.scene.images[i].numel() for i in floats.scene.train)
    assert floats.view(1) is floats.view(1)


def test_a_resized_image_is_served_with_the_values_its_cache_file_gives_later_runs(tmp_path, monkeypatch):
    """The first run resizes in float; later runs read the 8-bit cache file. Both get the same image (and so the
    compact 8-bit copy applies from the first run on)."""
    from data_fixtures import copy_of
    from warpgs.data import compact_image, load_scene

    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    root = copy_of("orbit", tmp_path / "scene")
    first = load_scene(root, split="llff", downscale=2).view(0).image
    later = load_scene(root, split="llff", downscale=2).view(0).image
    assert torch.equal(first, later) and compact_image.pack(first) is not None


def test_views_without_training_views_fail_on_draw_naming_the_scene():
    views = TrainViews(SimpleNamespace(train=[], root="/data/empty"), "cpu", seed=0)
    with pytest.raises(ValueError, match="/data/empty has no training views"):
        views.next()


# ----- LossSet ------------------------------------------------------------------------------------------------
@pytest.fixture
def test_losses():
    @register_loss("_parts_mean", outputs=("rgb",), weight=2.0)
    def mean_rgb(render_out, batch, model, step):
        return render_out.rgb.mean()

    @register_loss("_parts_depth", outputs=("inv_depth",), weight=1.0, schedule=["linear", 1.0, 0.0, 0, 50])
    def depth(render_out, batch, model, step):
        return render_out.inv_depth.mean()

    yield
    unregister_loss("_parts_mean")
    unregister_loss("_parts_depth")


def test_loss_set_outputs_follow_terms_schedules_and_extensions(test_losses):
    losses = LossSet(resolve_terms({"_parts_mean": None, "_parts_depth": None}), always=["alpha"])
    assert losses.names == ["_parts_mean", "_parts_depth"]
    assert losses.outputs == ("rgb", "alpha", "inv_depth")
    assert losses.outputs_at(10, 100) == ("rgb", "alpha", "inv_depth")
    assert losses.outputs_at(60, 100) == ("rgb", "alpha")  # the depth term is scheduled to 0 from step 50
    out = SimpleNamespace(rgb=torch.full((2, 2, 3), 0.25), inv_depth=torch.full((2, 2, 1), 3.0))
    result = losses(out, {}, None, 25, 100)  # depth weight 1 -> 0 over steps 0..50: 0.5 at 25
    assert float(result.total) == pytest.approx(2.0 * 0.25 + 0.5 * 3.0)
    assert result.weights == {"_parts_mean": 2.0, "_parts_depth": 0.5}


def test_loss_set_without_schedules_renders_the_union_at_every_step(test_losses):
    losses = LossSet(resolve_terms({"_parts_mean": 1.0}))
    assert losses.outputs_at(0, 10) == losses.outputs_at(9, 10) == ("rgb",)


def test_unknown_loss_names_the_key_and_a_close_match():
    with pytest.raises(ValueError, match=r"losses\.dsim: unknown loss.*did you mean 'dssim'"):
        resolve_terms({"dsim": 0.2})


# ----- Evaluator ----------------------------------------------------------------------------------------------
def _shifted(view):
    return view.image + 0.1  # MSE 0.01 against the view's image: PSNR 20 dB


def test_evaluator_scores_the_test_views_and_keeps_a_history(tmp_path):
    scene = FakeScene()
    ev = Evaluator(scene, EvalConfig(lpips=False, max_views=1), "cpu", tmp_path, render=_shifted)
    m = ev.evaluate()
    assert m["split"] == "test" and m["num_views"] == 2 and sorted(m["per_view"]) == ["v04.png", "v05.png"]
    assert m["psnr"] == pytest.approx(20.0, abs=1e-3)
    assert m["lpips"] is None and "disabled" in m["lpips_unavailable"]

    entry, pm = ev.periodic(100, num_primitives=7, train_seconds=1.23456)
    assert pm["num_views"] == 1  # eval.max_views during training
    assert entry == {"step": 100, "psnr": pm["psnr"], "ssim": pm["ssim"], "lpips": None, "num_primitives": 7,
                     "train_seconds": 1.235}
    assert ev.history == [entry]
    restored = Evaluator(scene, EvalConfig(lpips=False), "cpu", tmp_path, render=_shifted)
    restored.load_state_dict(ev.state_dict())
    assert restored.history == ev.history


def test_evaluator_falls_back_to_training_views_and_reuses_kept_ones(tmp_path):
    scene = FakeScene(n=4, test=())
    views = TrainViews(scene, "cpu", seed=0)
    kept = views.view(2)
    ev = Evaluator(scene, EvalConfig(lpips=False), "cpu", tmp_path, render=_shifted, views=views)
    split, chosen = ev.eval_views()
    assert split == "train" and [v.index for v in chosen] == [0, 1, 2, 3]
    assert chosen[2] is kept


def test_evaluator_saves_renders_and_keeps_images_on_request(tmp_path):
    ev = Evaluator(FakeScene(), EvalConfig(lpips=False), "cpu", tmp_path, render=lambda v: v.image * 2.0)
    m = ev.evaluate(save_images=True, keep_images=1)
    assert sorted(p.name for p in (tmp_path / "renders" / "test").glob("*.png")) == ["v04.png", "v05.png"]
    assert list(m["images"]) == ["v04.png"]
    img = m["images"]["v04.png"]
    assert img.shape == (4, 5, 3) and float(img.max()) <= 1.0  # clamped as scored
    assert "images" not in ev.evaluate()


def test_evaluator_needs_a_render_callable(tmp_path):
    with pytest.raises(ValueError, match="render"):
        Evaluator(FakeScene(), EvalConfig(), "cpu", tmp_path, render=None)


# ----- Checkpointer -------------------------------------------------------------------------------------------
def _parts(seed=0, history=()):
    """A small but complete TrainingState: 30 Gaussians, their Adam, a module with its own Adam, a strategy."""
    gen = torch.Generator().manual_seed(seed)
    model = GaussianModel.from_points(torch.rand(30, 3, generator=gen), sh_degree=1, generator=gen)
    modules = nn.ModuleDict({"head": nn.Linear(2, 2)})
    module_opt = torch.optim.Adam([{"params": list(modules.parameters()), "lr": 1e-3, "name": "head"}])
    strategy = DensifyStrategy(StrategyConfig(), 1.0)
    strategy.initialize(model)
    scene = FakeScene()
    evaluator = Evaluator(scene, EvalConfig(lpips=False), "cpu", ".", render=_shifted)
    evaluator.history = list(history)
    return TrainingState(RunCounters(), model, build_optimizer(model), module_opt, modules, strategy, [],
                         TrainViews(scene, "cpu", seed=seed), evaluator, Config())


def _train_a_little(parts, steps=3):
    for step in range(steps):
        loss = sum(p.square().sum() for p in parts.model.params.values()) + parts.modules["head"].weight.sum()
        loss.backward()
        parts.optimizer.step()
        parts.module_optimizer.step()
        parts.optimizer.zero_grad()
        parts.module_optimizer.zero_grad()
        parts.views.next()
        c = parts.counters
        c.step, c.train_seconds, c.last_loss = step + 1, 0.5 * step, float(loss.detach())


def test_checkpointer_writes_the_known_keys_and_restores_every_part(tmp_path):
    parts = _parts(history=[{"step": 2, "psnr": 12.0}])
    _train_a_little(parts)
    saver = Checkpointer(tmp_path / "checkpoint.pt", "cpu", guard=NonFiniteGuard(lambda: parts.model.params.items()))
    assert saver.last_step == -1
    saver.save(parts)
    assert saver.last_step == 3
    rng_after_save = torch.rand(3)

    reader = Checkpointer(tmp_path / "checkpoint.pt", "cpu")
    state = reader.load()
    assert list(state) == CHECKPOINT_KEYS
    fresh = _parts(seed=1)
    fresh.model = reader.model_from(state)
    fresh.optimizer = build_optimizer(fresh.model)
    fresh.strategy.initialize(fresh.model)
    reader.restore(state, fresh)

    assert reader.last_step == 3
    assert fresh.counters == parts.counters
    assert fresh.evaluator.history == [{"step": 2, "psnr": 12.0}]
    for name, p in parts.model.params.items():
        assert torch.equal(fresh.model.params[name], p.detach()), name
    assert fresh.optimizer.state_dict()["param_groups"] == parts.optimizer.state_dict()["param_groups"]
    for i, s in parts.optimizer.state_dict()["state"].items():
        assert torch.equal(fresh.optimizer.state_dict()["state"][i]["exp_avg"], s["exp_avg"])
    assert torch.equal(fresh.modules["head"].weight, parts.modules["head"].weight)
    assert torch.equal(torch.rand(3), rng_after_save)  # the global RNG continues where the saved run was
    assert _draw(fresh.views, 6) == _draw(parts.views, 6)


def test_checkpointer_guard_keeps_the_last_good_checkpoint(tmp_path):
    parts = _parts()
    saver = Checkpointer(tmp_path / "checkpoint.pt", "cpu", guard=NonFiniteGuard(lambda: parts.model.params.items()))
    parts.counters.step = 5
    saver.save(parts)
    good = (tmp_path / "checkpoint.pt").read_bytes()
    with torch.no_grad():
        parts.model.params["means"][0, 0] = float("nan")
    parts.counters.step = 6
    with pytest.raises(NonFiniteError, match="step 6: parameter 'means'"):
        saver.save(parts)
    assert (tmp_path / "checkpoint.pt").read_bytes() == good and saver.last_step == 5
    Checkpointer(tmp_path / "other.pt", "cpu").save(parts)  # without a guard it writes what it is given
    assert math.isnan(float(Checkpointer(tmp_path / "other.pt", "cpu").load()["model"]["params"]["means"][0, 0]))


def test_checkpointer_without_a_file_says_so(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"--resume: no checkpoint at .*nothing\.pt"):
        Checkpointer(tmp_path / "nothing.pt", "cpu").load()


# ----- the loop's running mean --------------------------------------------------------------------------------
def test_running_mean_starts_at_the_first_value_and_skips_none():
    m = RunningMean(weight=0.1)
    assert m.update(None) is None
    assert m.update(2.0) == 2.0
    assert m.update(None) == 2.0
    assert m.update(4.0) == pytest.approx(2.2)
    with pytest.raises(ValueError, match="weight"):
        RunningMean(weight=0.0)
