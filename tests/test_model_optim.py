"""Adam groups with the 3DGS learning rates, the position schedule, and optimizer-state surgery."""
import math

import pytest
import torch

from warpgs.model.gaussians import GaussianModel
from warpgs.train.optim import (OptimConfig, build_optimizer, exponential_lr, means_lr_at, set_param_values,
                          update_learning_rates, update_rows)


def model(n=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    m = GaussianModel.from_points(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g), sh_degree=1)
    m.add_extra("language", torch.randn(n, 4, generator=g))
    return m


def fill_adam_state(m, opt, steps=2, seed=1):
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        for p in m.params.values():
            p.grad = torch.randn(p.shape, generator=g)
        opt.step()


def test_groups_and_learning_rates():
    m = model()
    opt = build_optimizer(m, OptimConfig(extras_lr={"language": 0.01}), scene_extent=4.0)
    lrs = {g["name"]: g["lr"] for g in opt.param_groups}
    assert lrs == {"means": pytest.approx(1.6e-4 * 4), "log_scales": 5e-3, "quats": 1e-3,
                   "logit_opacities": 2.5e-2, "sh0": 2.5e-3, "shN": pytest.approx(2.5e-3 / 20), "language": 0.01}
    assert all(g["params"][0] is m.params[g["name"]] for g in opt.param_groups)
    assert opt.defaults["eps"] == 1e-15
    with pytest.raises(ValueError, match="scene_extent"):
        build_optimizer(m, scene_extent=0.0)
    with pytest.raises(ValueError, match="extras_lr"):
        build_optimizer(m, OptimConfig(extras_lr={"nope": 1.0}))
    with pytest.raises(ValueError, match="quats_lr"):
        OptimConfig(quats_lr=-1.0)


def test_position_schedule_hits_its_ends():
    cfg = OptimConfig()
    assert means_lr_at(0, cfg, 2.0, 1000) == pytest.approx(1.6e-4 * 2)
    assert means_lr_at(1000, cfg, 2.0, 1000) == pytest.approx(1.6e-6 * 2)
    assert means_lr_at(5000, cfg, 2.0, 1000) == pytest.approx(1.6e-6 * 2)  # held after the end
    assert means_lr_at(500, cfg, 2.0, 1000) == pytest.approx(math.sqrt(1.6e-4 * 1.6e-6) * 2)  # log-linear
    assert exponential_lr(0, 1.0, 0.1, 10, delay_steps=10, delay_mult=0.01) == pytest.approx(0.01)
    assert exponential_lr(10, 1.0, 0.1, 10, delay_steps=10, delay_mult=0.01) == pytest.approx(0.1)
    m = model()
    opt = build_optimizer(m, cfg, 2.0)
    lr = update_learning_rates(opt, 1000, cfg, 2.0, 1000)
    assert [g["lr"] for g in opt.param_groups if g["name"] == "means"] == [lr]
    with pytest.raises(ValueError, match="max_steps"):
        means_lr_at(0, cfg, 1.0, 0)


def test_position_schedule_of_a_longer_run():
    """means_lr_steps: a 1000-step run on a 10k decay (configs/sparse_llff_baseline.yaml) ends at that decay's
    step-1000 value, 10^(-0.2) of its start, not at means_lr_final."""
    cut = OptimConfig(means_lr_steps=10_000)
    assert means_lr_at(1000, cut, 1.0, 1000) == pytest.approx(1.6e-4 * 10 ** -0.2)
    assert means_lr_at(1000, cut, 1.0, 1000) == means_lr_at(1000, OptimConfig(), 1.0, 10_000)
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="means_lr_steps"):
            OptimConfig(means_lr_steps=bad)


def test_update_rows_keeps_adam_state_aligned():
    m = model()
    mlp = torch.nn.Linear(2, 2)
    opt = build_optimizer(m)
    opt.add_param_group({"params": list(mlp.parameters()), "lr": 1e-3, "name": "mlp"})
    for q in mlp.parameters():
        q.grad = torch.ones_like(q)
    fill_adam_state(m, opt)
    mlp_state = {id(p): opt.state[p]["exp_avg"].clone() for p in mlp.parameters()}
    old = {n: (p.detach().clone(), {k: v.clone() for k, v in opt.state[p].items()}) for n, p in m.params.items()}
    keep = torch.tensor([True, False, True, True, False, True])
    append = {n: torch.full((2, *p.shape[1:]), 7.0) for n, p in m.params.items()}
    update_rows(m, opt, keep=keep, append=append)

    assert m.num_primitives == 6
    for g in opt.param_groups:
        if g["name"] == "mlp":
            assert all(torch.equal(opt.state[p]["exp_avg"], mlp_state[id(p)]) for p in g["params"])
            continue
        p = g["params"][0]
        assert p is m.params[g["name"]] and p.requires_grad
        values, state = old[g["name"]]
        assert torch.equal(p[:4].detach(), values[keep]) and (p[4:] == 7.0).all()
        for key in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(opt.state[p][key][:4], state[key][keep])
            assert (opt.state[p][key][4:] == 0).all()
        assert torch.equal(opt.state[p]["step"], state["step"])
    fill_adam_state(m, opt, steps=1)  # the optimizer still runs on the new parameters
    assert all(torch.isfinite(p).all() for p in m.params.values())


def test_update_rows_errors():
    m = model()
    opt = build_optimizer(m)
    with pytest.raises(ValueError, match="append"):
        update_rows(m, opt, append={"means": torch.zeros(1, 3)})
    with pytest.raises(ValueError, match="keep"):
        update_rows(m, opt, keep=torch.ones(5, dtype=torch.bool))


def test_set_param_values_zeroes_only_that_state():
    m = model()
    opt = build_optimizer(m)
    fill_adam_state(m, opt)
    means_avg = opt.state[m.means]["exp_avg"].clone()
    set_param_values(m, opt, "logit_opacities", torch.full((6,), -3.0))
    p = m.params["logit_opacities"]
    assert (p == -3.0).all() and (opt.state[p]["exp_avg"] == 0).all() and (opt.state[p]["exp_avg_sq"] == 0).all()
    assert torch.equal(opt.state[m.means]["exp_avg"], means_avg)
    with pytest.raises(ValueError, match="values"):
        set_param_values(m, opt, "logit_opacities", torch.zeros(5))


def test_checkpoint_resume_after_resizing():
    m = model()
    opt = build_optimizer(m)
    fill_adam_state(m, opt)
    update_rows(m, opt, keep=torch.tensor([0, 2, 3]))  # the model shrank after building the optimizer
    fill_adam_state(m, opt, steps=1)
    state, opt_state = m.to_dict(), opt.state_dict()

    m2 = GaussianModel.from_dict(state)
    opt2 = build_optimizer(m2)
    opt2.load_state_dict(opt_state)  # same group order, matching sizes
    assert list(m2.params) == list(m.params)
    for g1, g2 in zip(opt.param_groups, opt2.param_groups):
        p1, p2 = g1["params"][0], g2["params"][0]
        assert g1["name"] == g2["name"] and torch.equal(p1, p2)
        assert torch.equal(opt.state[p1]["exp_avg_sq"], opt2.state[p2]["exp_avg_sq"])


def test_fused_adam_matches_foreach_through_row_surgery():
    """adam_kernel="fused" (the CUDA default) takes the same steps as torch's foreach Adam, also after rows are
    kept, appended (zero moments) and an opacity reset; "auto" is foreach on the CPU."""
    assert not build_optimizer(model(), OptimConfig()).defaults.get("fused")
    with pytest.raises(ValueError, match="adam_kernel"):
        OptimConfig(adam_kernel="sometimes")
    runs = {}
    for kernel in ("fused", "foreach"):
        m = model(n=9)
        opt = build_optimizer(m, OptimConfig(adam_kernel=kernel), scene_extent=2.0)
        assert bool(opt.defaults.get("fused")) == (kernel == "fused")
        fill_adam_state(m, opt, steps=3)
        update_rows(m, opt, keep=torch.tensor([0, 2, 3, 5, 8]),
                    append={k: v.detach()[:2] * 0.5 for k, v in m.params.items()})
        set_param_values(m, opt, "logit_opacities", m.logit_opacities.detach().clamp_max(-4.0))
        fill_adam_state(m, opt, steps=3, seed=2)
        runs[kernel] = {k: v.detach().clone() for k, v in m.params.items()}
    moved = max((runs["fused"][k] - model(n=9).params[k][:1]).abs().max().item() for k in ("sh0",))
    assert moved > 1e-4  # the steps did something
    for k, v in runs["foreach"].items():
        torch.testing.assert_close(runs["fused"][k], v, rtol=1e-5, atol=1e-6, msg=k)
