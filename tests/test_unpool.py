"""Proximity-guided unpooling (train/unpool.py): midpoints of long nearest-neighbour links, once per pair, the
longest first under the budget, and its place in the strategy's refine."""
import torch

from warpgs.model.gaussians import GaussianModel, knn
from warpgs.train.optim import build_optimizer
from warpgs.train.strategy import DensifyStrategy, StrategyConfig
from warpgs.train.unpool import midpoint_rows


def model_at(points, seed=0):
    points = torch.as_tensor(points, dtype=torch.float32)
    n = len(points)
    g = torch.Generator().manual_seed(seed)
    m = GaussianModel(points, torch.randn(n, 3, generator=g) * 0.1 - 3.0, torch.randn(n, 4, generator=g),
                      torch.randn(n, generator=g), torch.randn(n, 1, 3, generator=g), torch.randn(n, 3, 3, generator=g))
    m.add_extra("language", torch.randn(n, 4, generator=g))
    return m


def test_knn_matches_brute_force_and_never_returns_the_point_itself():
    g = torch.Generator().manual_seed(1)
    p = torch.randn(200, 3, generator=g)
    p[7] = p[3]  # a duplicate: each is the other's nearest, at distance 0
    d, idx = knn(p, 4)
    full = torch.cdist(p.double(), p.double())
    full.fill_diagonal_(float("inf"))
    ref = full.topk(4, dim=1, largest=False)
    torch.testing.assert_close(d.double(), ref.values, atol=1e-5, rtol=1e-5)
    assert (idx != torch.arange(200)[:, None]).all()
    assert idx[7, 0] == 3 and idx[3, 0] == 7 and d[3, 0] == 0


def test_knn_with_more_coincident_points_than_neighbours_still_skips_the_point_itself():
    p = torch.cat([torch.zeros(6, 3), torch.tensor([[1.0, 0, 0], [3.0, 0, 0]])])  # six at the origin, k + 1 = 3
    d, idx = knn(p, 2)
    assert d.shape == idx.shape == (8, 2) and d.dtype == torch.float32 and idx.dtype == torch.int64
    assert (idx != torch.arange(8)[:, None]).all()
    assert (d[:6] == 0).all() and (idx[:6] < 6).all()
    torch.testing.assert_close(d[6], torch.tensor([1.0, 1.0]))
    torch.testing.assert_close(d[7], torch.tensor([2.0, 3.0]))
    assert knn(p[:1], 3)[0].shape == (1, 0)  # a lone point has no neighbours


def test_a_long_link_gets_one_midpoint_with_its_ends_mean_and_the_fainter_opacity():
    # 0 and 1 are close; 2 is far from both: links 0-1 (short, twice), 2-1 (long).
    m = model_at([[0.0, 0, 0], [0.001, 0, 0], [1.0, 0, 0]])
    rows = midpoint_rows(m.params, k=1, min_distance=0.5, room=10)
    assert len(rows["means"]) == 1
    torch.testing.assert_close(rows["means"][0], torch.tensor([0.5005, 0, 0]))
    p = {k: v.detach() for k, v in m.params.items()}
    torch.testing.assert_close(rows["log_scales"][0], 0.5 * (p["log_scales"][1] + p["log_scales"][2]))
    torch.testing.assert_close(rows["sh0"][0], 0.5 * (p["sh0"][1] + p["sh0"][2]))
    assert rows["logit_opacities"][0] == torch.minimum(p["logit_opacities"][1], p["logit_opacities"][2])
    assert torch.equal(rows["quats"][0], p["quats"][1]) and torch.equal(rows["language"][0], p["language"][1])
    assert set(rows) == set(m.params)


def test_a_pair_found_from_both_ends_is_filled_once_and_the_budget_keeps_the_longest():
    m = model_at([[0.0, 0, 0], [1.0, 0, 0]])
    assert len(midpoint_rows(m.params, k=1, min_distance=0.5, room=10)["means"]) == 1
    # Three pairs, far from each other, of lengths 1, 3 and 2: room for two keeps lengths 3 and 2.
    m = model_at([[0.0, 0, 0], [1.0, 0, 0], [100.0, 0, 0], [103.0, 0, 0], [-100.0, 0, 0], [-102.0, 0, 0]])
    rows = midpoint_rows(m.params, k=1, min_distance=0.5, room=2)
    assert sorted(rows["means"][:, 0].tolist()) == [-101.0, 101.5]
    assert len(midpoint_rows(m.params, k=1, min_distance=0.5, room=0)["means"]) == 0
    assert len(midpoint_rows(m.params, k=1, min_distance=5.0, room=9)["means"]) == 0  # nothing that long


def test_the_strategy_unpools_at_its_refines_within_the_budget_with_the_optimizer_aligned():
    g = torch.Generator().manual_seed(3)
    m = model_at(torch.rand(40, 3, generator=g) * 2 + torch.tensor([0, 0, 3.0]))
    opt = build_optimizer(m)
    for p in m.params.values():
        p.grad = torch.randn(p.shape, generator=g) * 1e-3
    opt.step()
    cfg = StrategyConfig(unpool_every=2, unpool_k=3, unpool_distance=0.05, max_primitives=70, prune_opacity=0.0)
    s = DensifyStrategy(cfg, scene_extent=1.0)
    s.initialize(m)
    before = m.means.detach().clone()
    off = s.refine(m, opt, step=100)  # the 1st refine (100 // 100 = 1): not an unpooling one
    assert off["unpooled"] == 0 and m.num_primitives == 40
    on = s.refine(m, opt, step=200)
    assert on["unpooled"] == 30 and m.num_primitives == 70  # capped by the budget
    assert torch.equal(m.means[:40].detach(), before)
    for group in opt.param_groups:
        p = group["params"][0]
        assert p.shape[0] == 70 and (opt.state[p]["exp_avg"][40:] == 0).all()
    assert s.refine(m, opt, step=400)["unpooled"] == 0  # the budget is full


def test_a_training_run_with_unpooling_fills_gaps_and_stays_finite(tmp_path):
    """The config key reaches the trainer's strategy: a short run logs unpooled primitives at its refines and ends
    with a finite model under the budget."""
    from train_fixtures import quick_overrides

    from warpgs.train.trainer import Trainer

    reports = []
    overrides = quick_overrides(tmp_path, steps=25, **{"strategy.unpool_every": 1, "strategy.unpool_distance": 0.01})
    trainer = Trainer(None, overrides=overrides, quiet=True,
                      callbacks=[lambda tr, step, info: info["densify"] and reports.append(info["densify"])])
    result = trainer.fit()
    assert reports and sum(r.get("unpooled", 0) for r in reports) > 0
    assert result.num_primitives <= 6000  # quick_overrides' budget
    assert all(torch.isfinite(p).all() for p in trainer.model.params.values())


def test_auto_is_off_with_a_few_training_views_and_at_every_refine_with_more():
    import pytest

    from warpgs.train.unpool import AUTO_OFF_MAX_VIEWS, unpool_every_for, unpool_note

    assert [unpool_every_for("auto", n) for n in (2, 3, AUTO_OFF_MAX_VIEWS, AUTO_OFF_MAX_VIEWS + 1, 24)] == \
        [0, 0, 0, 1, 1]
    assert unpool_every_for(0, 24) == 0 and unpool_every_for(3, 2) == 3  # a number is taken as given
    off = unpool_note("auto", 0, 3)
    assert "unpooling off" in off and f"more than {AUTO_OFF_MAX_VIEWS}" in off and "3 training views" in off
    assert unpool_note("auto", 1, 6) == unpool_note(1, 1, 6) == "; unpooling"
    assert unpool_note(2, 2, 6) == "; unpooling every 2 refines" and unpool_note(0, 0, 6) == ""
    with pytest.raises(ValueError, match="unpool_every"):  # the strategy cannot count views: the trainer resolves it
        DensifyStrategy(StrategyConfig(unpool_every="auto"), scene_extent=1.0)


def test_the_config_takes_auto_and_names_the_key_of_a_bad_period():
    from pathlib import Path

    import pytest

    from warpgs.config import ConfigError, load_config

    preset = Path(__file__).resolve().parent.parent / "configs" / "sparse_llff.yaml"
    assert load_config(preset).strategy.unpool_every == "auto"
    assert load_config(None, overrides=["strategy.unpool_every=2"]).strategy.unpool_every == 2
    for bad in ("sometimes", "-1", "0.5"):
        with pytest.raises(ConfigError, match="strategy.unpool_every"):
            load_config(None, overrides=[f"strategy.unpool_every={bad}"])


def test_a_training_run_resolves_auto_by_its_training_views(tmp_path):
    """strategy.unpool_every=auto reaches the trainer's strategy as a number for the scene's training-view count,
    and unpools when that count is above the rule's bound."""
    from train_fixtures import quick_overrides

    from warpgs.train.trainer import Trainer
    from warpgs.train.unpool import AUTO_OFF_MAX_VIEWS, unpool_every_for

    reports = []
    overrides = quick_overrides(tmp_path, steps=25, **{"strategy.unpool_every": "auto",
                                                       "strategy.unpool_distance": 0.01})
    trainer = Trainer(None, overrides=overrides, quiet=True,
                      callbacks=[lambda tr, step, info: info["densify"] and reports.append(info["densify"])])
    views = len(trainer.scene.train)
    assert trainer.strategy.config.unpool_every == unpool_every_for("auto", views)
    trainer.fit()
    unpooled = sum(r.get("unpooled", 0) for r in reports)
    assert (unpooled > 0) == (views > AUTO_OFF_MAX_VIEWS)
