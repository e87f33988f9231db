"""Densification: which primitives are cloned, split, pruned; opacity reset; the budget; the 2D gradients."""
import math

import pytest
import torch

from warpgs.model.gaussians import GaussianModel, SurfelModel, quat_to_rotmat
from warpgs.train.optim import build_optimizer
from warpgs.train.screen_geometry import screen_grads_from_means_grad, screen_radii
from warpgs.train.strategy import DensifyStrategy, PruningWarning, StrategyConfig

W = H = 100
HIGH = 1e-5  # px gradient -> NDC norm 1e-5 * 50 = 5e-4 > 2e-4
LOW = 1e-7
VIEW = torch.eye(4)
K = torch.tensor([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])


def make(scales, opacities, cls=GaussianModel, seed=0):
    n = len(scales)
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.randn(n, 4, generator=g)
    sc = torch.tensor(scales, dtype=torch.float32)[:, None].repeat(1, cls.num_scales)
    op = torch.tensor(opacities, dtype=torch.float32)
    m = cls(means, sc.log(), quats, torch.log(op / (1 - op)), torch.randn(n, 1, 3, generator=g),
            torch.randn(n, 3, 3, generator=g))
    m.add_extra("language", torch.randn(n, 4, generator=g))
    return m


def adam_with_state(m):
    opt = build_optimizer(m)
    g = torch.Generator().manual_seed(5)
    for p in m.params.values():
        p.grad = torch.randn(p.shape, generator=g)
    opt.step()
    return opt


def feed(strategy, m, opt, step, grad_px, visible=None, **kw):
    n = m.num_primitives
    g2 = torch.zeros(n, 2)
    g2[:, 0] = torch.as_tensor(grad_px, dtype=torch.float32)
    vis = torch.ones(n, dtype=torch.bool) if visible is None else visible
    return strategy.step_post_backward(m, opt, step, visible=vis, viewmat=VIEW, K=K, width=W, height=H,
                                       grad2d=g2, **kw)


def test_clone_split_prune_and_adam_alignment():
    #           0: small+hot  1: large+hot  2: small+cold  3: faint+hot  4: large+cold
    m = make([0.005, 0.1, 0.005, 0.005, 0.1], [0.5, 0.5, 0.5, 0.001, 0.5])
    opt = adam_with_state(m)
    before = {n: (p.detach().clone(), opt.state[p]["exp_avg"].clone()) for n, p in m.params.items()}
    s = DensifyStrategy(StrategyConfig(), scene_extent=1.0)
    s.initialize(m)
    assert feed(s, m, opt, 599, [HIGH, HIGH, LOW, HIGH, LOW]) is None  # not a refine step
    report = feed(s, m, opt, 600, [HIGH, HIGH, LOW, HIGH, LOW])
    assert report == {"step": 600, "cloned": 1, "split": 1, "pruned": 1, "unpooled": 0, "budget_dropped": 0,
                      "num_primitives": 6,
                      "pruned_by": {"opacity": 1, "invisible": 0, "world_size": 0, "screen_size": 0}}
    keep = [0, 2, 4]
    for name, p in m.params.items():
        old, old_avg = before[name]
        assert opt.param_groups[[g["name"] for g in opt.param_groups].index(name)]["params"][0] is p
        assert torch.equal(p[:3].detach(), old[keep]), name  # kept rows, in order
        if name not in ("means", "log_scales"):
            assert torch.equal(p[3].detach(), old[0]) and torch.equal(p[4:6].detach(), old[[1, 1]]), name
        assert torch.equal(opt.state[p]["exp_avg"][:3], old_avg[keep]) and (opt.state[p]["exp_avg"][3:] == 0).all()
    assert torch.equal(m.means[3], before["means"][0][0])  # clone in place
    torch.testing.assert_close(m.scales[4:], before["log_scales"][0][[1, 1]].exp() / 1.6)
    offsets = m.means[4:].detach() - before["means"][0][1]
    assert (offsets.norm(dim=1) > 0).all() and (offsets.norm(dim=1) < 0.1 * 6).all()  # sampled, within 6 sigma
    assert s.stats.grad_accum.shape == (6,) and (s.stats.grad_accum == 0).all() and (s.stats.count == 0).all()


def test_grads_average_over_visible_steps_only():
    m = make([0.005] * 3, [0.5] * 3)
    opt = adam_with_state(m)
    s = DensifyStrategy()
    s.initialize(m)
    # Primitive 0 is hot when seen once; primitive 1 is hot once in two visible steps (avg below threshold
    # only if cold steps count); primitive 2 is hot but never visible.
    feed(s, m, opt, 10, [HIGH, HIGH, HIGH], visible=torch.tensor([True, True, False]))
    feed(s, m, opt, 11, [0.0, 0.0, HIGH], visible=torch.tensor([False, True, False]))
    torch.testing.assert_close(s.stats.average_grads(), torch.tensor([HIGH * 50, HIGH * 25, 0.0]))
    assert s.stats.count.tolist() == [1, 2, 0]


def test_refine_and_reset_schedule():
    cfg = StrategyConfig(refine_start=500, refine_every=100, refine_stop=1000, reset_every=700)
    m = make([0.005] * 4, [0.5] * 4)
    opt = adam_with_state(m)
    s = DensifyStrategy(cfg)
    s.initialize(m)
    refined = [st for st in range(0, 1200, 50) if (r := feed(s, m, opt, st, [LOW] * m.num_primitives)) and "cloned" in r]
    assert refined == [600, 700, 800, 900]  # > start, < stop, every 100
    assert feed(s, m, opt, 1000, [HIGH] * m.num_primitives) is None and m.num_primitives == 4


def test_opacity_reset_clamps_and_zeroes_state():
    m = make([0.005] * 3, [0.9, 0.004, 0.5])
    opt = adam_with_state(m)
    means_state = opt.state[m.means]["exp_avg"].clone()
    start = m.opacities.detach().clone()  # (the Adam step above moved them a little)
    assert start[1] < 0.01 < start[2]
    s = DensifyStrategy(StrategyConfig(refine_start=5000))
    s.initialize(m)
    report = feed(s, m, opt, 3000, [LOW] * 3)
    assert report["opacity_reset"] is True
    torch.testing.assert_close(m.opacities, torch.stack([torch.tensor(0.01), start[1], torch.tensor(0.01)]))
    p = m.logit_opacities
    assert (opt.state[p]["exp_avg"] == 0).all() and torch.equal(opt.state[m.means]["exp_avg"], means_state)


def test_size_pruning_starts_late():
    # 0: huge in world (0.5 > 0.1 x extent); 1: ordinary; both cold.
    m = make([0.5, 0.005], [0.5, 0.5])
    opt = adam_with_state(m)
    s = DensifyStrategy(StrategyConfig(size_prune_start=3000, prune_screen_radius=0))
    s.initialize(m)
    assert feed(s, m, opt, 600, [LOW, LOW])["pruned"] == 0
    assert feed(s, m, opt, 3100, [LOW, LOW])["pruned"] == 1 and m.num_primitives == 1
    assert m.scales.max() < 0.1


def test_oversized_primitive_with_a_high_gradient_is_split_before_the_size_rule():
    # As 3DGS and gsplat (grow, then prune): world threshold 0.1 x extent 1 = 0.1. 0: 0.12, hot -> split into two
    # children of 0.075 that pass; 1: 0.12, cold -> pruned; 2: 0.5, hot -> children 0.31 still too big, pruned;
    # 3: ordinary, cold -> kept.
    m = make([0.12, 0.12, 0.5, 0.005], [0.5, 0.5, 0.5, 0.5])
    opt = adam_with_state(m)
    s = DensifyStrategy(StrategyConfig(size_prune_start=3000))
    s.initialize(m)
    with pytest.warns(PruningWarning, match="world size"):  # 3 of 4 pruned
        report = feed(s, m, opt, 3100, [HIGH, LOW, HIGH, LOW])
    assert report["pruned_by"]["world_size"] == 3
    assert report["split"] == 2 and report["pruned"] == 1 + 2 and report["cloned"] == 0
    assert m.num_primitives == 3
    kept = sorted(m.scales.amax(1).tolist())
    assert kept[0] == pytest.approx(0.005, rel=0.02) and kept[1:] == pytest.approx([0.12 / 1.6] * 2, rel=0.02)
    assert all(len(opt.state[p]["exp_avg"]) == 3 for p in m.params.values())


def test_flagged_primitives_are_not_copied():
    # A faint (opacity rule) hot primitive would pass its opacity to its copies: neither cloned nor split.
    m = make([0.005, 0.5, 0.005], [0.001, 0.001, 0.5])
    opt = adam_with_state(m)
    s = DensifyStrategy(StrategyConfig())
    s.initialize(m)
    with pytest.warns(PruningWarning, match="opacity"):  # 2 of 3 pruned
        report = feed(s, m, opt, 600, [HIGH, HIGH, LOW])
    assert report["cloned"] == 0 and report["split"] == 0 and report["pruned"] == 2 and m.num_primitives == 1


def test_primitives_the_renderer_cannot_see_are_pruned():
    # Opacities 0.02 and 0.5, both above prune_opacity (0.005); with the renderer's alpha_min at 0.05 the first
    # never reaches a tile (no gradient, ever), so it goes; with the default alpha_min it stays.
    for alpha_min, pruned in ((0.05, 1), (1 / 255, 0)):
        m = make([0.005, 0.005], [0.02, 0.5])
        opt = adam_with_state(m)
        s = DensifyStrategy(StrategyConfig(prune_screen_radius=0), invisible_below=alpha_min)
        s.initialize(m)
        assert feed(s, m, opt, 600, [LOW, LOW])["pruned"] == pruned
        assert m.opacities.min() > alpha_min


def test_screen_size_pruning():
    # Both small in the world (world pruning off), but 0 sits right in front of the camera: large on screen.
    m = make([0.005, 0.005], [0.5, 0.5])
    with torch.no_grad():
        m.params["means"][0] = torch.tensor([0.0, 0.0, 0.05])
    opt = adam_with_state(m)
    s = DensifyStrategy(StrategyConfig(prune_world_scale=0, prune_screen_size=0.15))
    s.initialize(m)
    feed(s, m, opt, 3050, [LOW, LOW])
    assert s.stats.max_radii[0] > 15 > s.stats.max_radii[1]  # px, on a 100 px image
    torch.testing.assert_close(s.stats.max_screen, s.stats.max_radii / 100)
    report = feed(s, m, opt, 3100, [LOW, LOW])
    assert report["pruned"] == 1 and report["pruned_by"]["screen_size"] == 1
    assert m.means[0, 2] > 1.0  # the near one went


def test_without_a_screen_rule_no_radii_are_computed_or_kept():
    m = make([0.005, 0.005], [0.5, 0.5])
    with torch.no_grad():
        m.params["means"][0] = torch.tensor([0.0, 0.0, 0.05])  # large on screen, as above
    s = DensifyStrategy(StrategyConfig(prune_world_scale=0))  # the default: no screen-size rule
    s.initialize(m)
    obs = s.observe(m, visible=torch.ones(2, dtype=torch.bool), viewmat=VIEW, K=K, width=W, height=H,
                    grad2d=torch.full((2, 2), HIGH))
    assert obs["radii"] is None and obs["screen"] is None
    both = s.merge_observations([obs, obs])
    assert both["radii"] is None and both["count"].tolist() == [2, 2]
    s.add_observations(both)
    assert s.stats.max_radii.tolist() == [0.0, 0.0] and s.stats.count.tolist() == [2, 2]
    ruled = DensifyStrategy(StrategyConfig(prune_world_scale=0, prune_screen_size=0.15))
    ruled.initialize(m)
    seen = ruled.observe(m, visible=torch.ones(2, dtype=torch.bool), viewmat=VIEW, K=K, width=W, height=H,
                         grad2d=torch.full((2, 2), HIGH))
    assert seen["radii"][0] > 15 and ruled.merge_observations([obs, seen])["radii"][0] > 15


def test_screen_size_is_a_fraction_of_the_larger_side_over_all_views():
    # Radius 30 px: 15% of a 200x100 image, 30% of 100x100; the largest fraction since the last refine counts.
    m = make([0.005], [0.5])
    s = DensifyStrategy(StrategyConfig(prune_screen_size=0.2))
    s.initialize(m)
    vis = torch.ones(1, 1, dtype=torch.bool)
    s.accumulate(torch.zeros(1, 1, 2), vis, torch.tensor([[30.0]]), 200, 100)
    assert s.stats.max_screen.item() == pytest.approx(0.15) and not s.prune_rules(m, 3100)["screen_size"].any()
    s.accumulate(torch.zeros(1, 1, 2), vis, torch.tensor([[30.0]]), 100, 100)
    assert s.stats.max_screen.item() == pytest.approx(0.3) and s.prune_rules(m, 3100)["screen_size"].all()
    assert not s.prune_rules(m, 3000)["screen_size"].any()  # only after size_prune_start
    s.accumulate(torch.zeros(1, 1, 2), ~vis, torch.tensor([[90.0]]), 100, 100)  # not visible: not counted
    assert s.stats.max_screen.item() == pytest.approx(0.3)


def test_budget_keeps_highest_gradients():
    m = make([0.005] * 5, [0.5] * 5)
    opt = adam_with_state(m)
    s = DensifyStrategy(StrategyConfig(max_primitives=7))
    s.initialize(m)
    before = m.means.detach().clone()
    report = feed(s, m, opt, 600, [2 * HIGH, 5 * HIGH, LOW, 4 * HIGH, 3 * HIGH])
    assert report["cloned"] == 2 and report["budget_dropped"] == 2 and m.num_primitives == 7
    assert torch.equal(m.means[5:].detach(), before[[1, 3]])  # the two hottest were cloned


def test_budget_never_exceeded_over_a_run():
    cfg = StrategyConfig(max_primitives=40, refine_start=0, refine_every=2, reset_every=0, dense_scale=0.02)
    g = torch.Generator().manual_seed(0)
    m = make((torch.rand(10, generator=g) * 0.04 + 0.001).tolist(), [0.5] * 10)
    opt = adam_with_state(m)
    s = DensifyStrategy(cfg)
    s.initialize(m)
    counts = []
    for step in range(1, 60):
        n = m.num_primitives
        grads = torch.rand(n, generator=g) * 4 * HIGH
        feed(s, m, opt, step, grads, visible=torch.rand(n, generator=g) > 0.2)
        counts.append(m.num_primitives)
    assert max(counts) == 40 and all(c <= 40 for c in counts)
    assert all(len(opt.state[p]["exp_avg"]) == m.num_primitives for p in m.params.values())


def test_initialize_rejects_models_over_budget():
    m = make([0.005] * 5, [0.5] * 5)
    with pytest.raises(ValueError, match="max_primitives"):
        DensifyStrategy(StrategyConfig(max_primitives=4)).initialize(m)


def test_surfel_split_stays_in_plane():
    m = make([0.1, 0.1], [0.5, 0.5], cls=SurfelModel)
    opt = adam_with_state(m)
    s = DensifyStrategy()
    s.initialize(m)
    parents = m.means.detach().clone()
    normals = quat_to_rotmat(m.quats.detach())[:, :, 2]
    feed(s, m, opt, 600, [HIGH, HIGH])
    assert m.num_primitives == 4 and m.log_scales.shape == (4, 2)
    offsets = m.means.detach() - parents.repeat_interleave(2, 0)
    torch.testing.assert_close((offsets * normals.repeat_interleave(2, 0)).sum(1), torch.zeros(4), atol=1e-6, rtol=0)
    assert (offsets.norm(dim=1) > 1e-4).all()


def test_split_of_a_flat_primitive_keeps_finite_log_scales():
    """Regression (found while writing tests/stress): a split primitive whose thinnest axis has a log-scale
    below ~-104 (exp() underflows to 0 in float32) used to get children with log-scale -inf."""
    m = make([0.1, 0.1], [0.5, 0.5])
    with torch.no_grad():
        m.params["log_scales"][0, 2] = -120.0
    opt = build_optimizer(m)
    s = DensifyStrategy()
    s.initialize(m)
    assert feed(s, m, opt, 600, [HIGH, HIGH])["split"] == 2
    assert torch.isfinite(m.log_scales).all()
    expected = torch.tensor([math.log(0.1), math.log(0.1), -120.0]) - math.log(1.6)  # parent / split_shrink
    torch.testing.assert_close(m.log_scales.detach()[:2], expected.expand(2, 3))  # both rows: primitive 0's children


def project(means, viewmat, K):
    p = means @ viewmat[:3, :3].T + viewmat[:3, 3]
    return torch.stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]], 1)


def test_screen_grad_surrogate_is_exact_through_2d_means():
    g = torch.Generator().manual_seed(0)
    angle = 0.3
    view = torch.eye(4)
    view[:3, :3] = torch.tensor([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]])
    view[:3, 3] = torch.tensor([0.2, -0.1, 4.0])
    means = (torch.randn(20, 3, generator=g)).double().requires_grad_()
    weights = torch.randn(20, 2, generator=g).double()
    (project(means, view.double(), K.double()) * weights).sum().backward()
    got = screen_grads_from_means_grad(means, means.grad, view.double(), K.double())
    torch.testing.assert_close(got, weights)


def test_step_post_backward_uses_means_grad():
    m = make([0.005] * 3, [0.5] * 3)
    opt = build_optimizer(m)
    s = DensifyStrategy()
    s.initialize(m)
    with pytest.raises(ValueError, match="means.grad"):
        s.step_post_backward(m, opt, 1, visible=torch.ones(3, dtype=torch.bool), viewmat=VIEW, K=K, width=W, height=H)
    target = torch.tensor([[1e-4, 0.0], [0.0, -2e-4], [3e-4, 4e-4]])
    (project(m.means, VIEW, K) * target).sum().backward()
    s.step_post_backward(m, opt, 1, visible=torch.ones(3, dtype=torch.bool), viewmat=VIEW, K=K, width=W, height=H)
    torch.testing.assert_close(s.stats.grad_accum, (target * 50).norm(dim=1))


def test_batched_grad2d_scaled_by_camera_count():
    m = make([0.005] * 2, [0.5] * 2)
    s = DensifyStrategy()
    s.initialize(m)
    g2 = torch.tensor([[[1e-4, 0.0], [0.0, 0.0]], [[0.0, 0.0], [1e-4, 0.0]]])
    vis = torch.tensor([[True, False], [True, True]])
    s.step_post_backward(m, [], 1, visible=vis, viewmat=VIEW.expand(2, 4, 4), K=K.expand(2, 3, 3), width=W, height=H,
                         grad2d=g2)
    torch.testing.assert_close(s.stats.grad_accum, torch.tensor([1e-4 * 50 * 2, 1e-4 * 50 * 2]))
    assert s.stats.count.tolist() == [2, 1]
    with pytest.raises(ValueError, match="grad2d"):
        s.step_post_backward(m, [], 2, visible=vis, viewmat=VIEW.expand(2, 4, 4), K=K.expand(2, 3, 3), width=W,
                             height=H)


def test_screen_radius_on_axis():
    m = make([0.02], [0.5])
    with torch.no_grad():
        m.params["means"][0] = torch.tensor([0.0, 0.0, 2.0])
    r = screen_radii(m, VIEW, K, W, H)
    assert r.item() == pytest.approx(3 * math.sqrt((100 * 0.02 / 2.0) ** 2 + 0.3), rel=1e-5)
    with torch.no_grad():
        m.params["means"][0, 2] = -1.0
    assert screen_radii(m, VIEW, K, W, H).item() == 0.0  # behind the camera


def test_state_dict_without_max_screen_loads():
    s = DensifyStrategy()
    s.initialize(make([0.005] * 3, [0.5] * 3))
    state = {k: v for k, v in s.state_dict().items() if k != "max_screen"}  # a checkpoint from before the key
    s.load_state_dict(state)
    assert torch.equal(s.stats.max_screen, torch.zeros(3))


def test_state_dict_resume_reproduces_splits():
    def run(resume):
        m = make([0.1, 0.1], [0.5, 0.5])
        opt = adam_with_state(m)
        s = DensifyStrategy()
        s.initialize(m)
        feed(s, m, opt, 590, [HIGH, HIGH])
        if resume:
            state = {k: (v.clone() if torch.is_tensor(v) else v) for k, v in s.state_dict().items()}
            s = DensifyStrategy()
            s.load_state_dict(state)
        feed(s, m, opt, 600, [HIGH, HIGH])
        return m.means.detach()

    assert torch.equal(run(False), run(True))


def test_model_resized_behind_the_strategy_is_caught():
    m = make([0.005] * 3, [0.5] * 3)
    s = DensifyStrategy()
    with pytest.raises(ValueError, match="initialize"):
        s.step_pre_backward(m, 0)
    s.initialize(m)
    m2 = make([0.005] * 4, [0.5] * 4)
    with pytest.raises(ValueError, match="model"):
        s.step_pre_backward(m2, 0)


@pytest.mark.parametrize("field,value", [("grad_threshold", -1.0), ("split_count", 1), ("max_primitives", 0),
                                         ("reset_opacity", 1.0), ("refine_every", 0)])
def test_config_errors_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        StrategyConfig(**{field: value})
    with pytest.raises(ValueError, match="scene_extent"):
        DensifyStrategy(scene_extent=float("nan"))
