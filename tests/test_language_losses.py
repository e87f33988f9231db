"""PPGS losses: bidirectional terms (stop-gradients really stop), beta, alternation, homoscedastic weighting,
and the registered terms on a tiny fake render."""
import pytest
import torch

from warpgs.model.gaussians import SurfelModel
from warpgs.language.bridge import BridgeMLP
from warpgs.language.losses import (BRIDGE_MODULE, SIGMA_MODULE, HomoscedasticWeights, LanguageContext,
                                    active_branch, beta_from_uncertainty, bidirectional_loss, color_bridge_loss,
                                    feature_bridge_loss, safe_norm)
from warpgs.language.settings import LanguageConfig
from warpgs.losses import compute_losses, resolve_losses
from warpgs.render.gaussians import RenderOutput


def _unit(x):
    return x / x.norm(dim=-1, keepdim=True)


def _gsum(t):
    """Sum of |grad| (0 when no gradient reached the tensor)."""
    return 0.0 if t.grad is None else float(t.grad.abs().sum())


def test_bidirectional_gradients_match_the_stop_gradient_formula():
    torch.manual_seed(0)
    theta = torch.randn(6, 3, requires_grad=True)  # "MLP weights": mlp_out = theta * x
    x = torch.randn(6, 3)
    params = torch.randn(6, 3, requires_grad=True)
    beta = torch.rand(6)
    mlp = theta * x
    bidirectional_loss(mlp, params, beta).backward()
    diff = (theta * x - params).detach()
    # term 1 only reaches the MLP, term 2 only the primitives' parameters
    assert torch.allclose(theta.grad, _unit(diff) * x, atol=1e-6)
    assert torch.allclose(params.grad, -beta[:, None] * _unit(diff), atol=1e-6)


def test_frozen_branch_and_disabled_pull():
    torch.manual_seed(1)
    theta = torch.randn(4, 2, requires_grad=True)
    params = torch.randn(4, 2, requires_grad=True)
    bidirectional_loss(theta * 2.0, params, 0.5, train_mlp=False).backward()
    assert _gsum(theta) == 0.0 and _gsum(params) > 0
    theta.grad = params.grad = None
    bidirectional_loss(theta * 2.0, params, 0.5, pull=False).backward()
    assert _gsum(params) == 0.0 and _gsum(theta) > 0


def test_value_sum_and_mean_and_zero_distance():
    mlp = torch.tensor([[3.0, 4.0], [0.0, 0.0]])
    params = torch.zeros(2, 2, requires_grad=True)
    assert float(bidirectional_loss(mlp, params, 0.1).detach()) == pytest.approx(5.0 * 1.1)
    assert float(bidirectional_loss(mlp, params, 0.1, reduction="mean").detach()) == pytest.approx(5.0 * 1.1 / 2)
    x = torch.zeros(3, requires_grad=True)
    safe_norm(x).backward()
    assert torch.equal(x.grad, torch.zeros(3))  # no NaN at zero distance


def test_beta_and_alternation():
    eps = torch.tensor([0.0, 0.5, 1.0])
    assert torch.allclose(beta_from_uncertainty(eps, 0.1), torch.tensor([0.1, 0.55, 1.0]))
    assert [active_branch(s, 10) for s in (0, 9, 10, 19, 20)] == ["color", "color", "language", "language", "color"]
    assert active_branch(123, 0) == "both"


def _surfels(n=30, seed=0):
    g = torch.Generator().manual_seed(seed)
    pts, cols = torch.rand(n, 3, generator=g), torch.rand(n, 3, generator=g)
    model = SurfelModel.from_points(pts, cols, sh_degree=0, generator=g)
    model.add_extra("lang", torch.randn(n, 4, generator=g))
    model.add_extra("lang_eps", torch.zeros(n, 1))
    return model


def test_bridge_losses_route_gradients_by_phase():
    model = _surfels()
    cfg = LanguageConfig(dim=4, alternate_period=5, bridge_position_scale=1.0)
    bridge = BridgeMLP(4, n_freqs=2, width=8, depth=2)
    batch = {"language": LanguageContext(cfg), "modules": torch.nn.ModuleDict({BRIDGE_MODULE: bridge})}
    # colour phase (step 0): L_f's MLP part is frozen, so the language head gets nothing from L_f
    feature_bridge_loss(batch, model, 0).backward()
    assert bridge.lang_head.weight.grad is None or float(bridge.lang_head.weight.grad.abs().sum()) == 0
    assert float(model.params["lang"].grad.abs().sum()) > 0  # the pull on the primitives stays on
    assert model.params["lang_eps"].grad is None  # beta does not train eps (beta_grad=False)
    model.zero_grad(set_to_none=True)
    bridge.zero_grad(set_to_none=True)
    batch.pop("_bridge_cache", None)
    # language phase (step 5): L_f trains the language head and, through the MLP, the centres
    feature_bridge_loss(batch, model, 5).backward()
    assert float(bridge.lang_head.weight.grad.abs().sum()) > 0
    assert float(model.params["means"].grad.abs().sum()) > 0
    assert bridge.color_head.weight.grad is None or float(bridge.color_head.weight.grad.abs().sum()) == 0
    model.zero_grad(set_to_none=True)
    bridge.zero_grad(set_to_none=True)
    batch.pop("_bridge_cache", None)
    color_bridge_loss(batch, model, 0).backward()
    assert float(bridge.color_head.weight.grad.abs().sum()) > 0
    assert float(model.params["sh0"].grad.abs().sum()) > 0


def test_position_gradient_scale_and_start():
    model = _surfels()
    bridge = BridgeMLP(4, n_freqs=2, width=8, depth=2)

    def means_grad(**opts):
        cfg = LanguageConfig(dim=4, alternate_period=0, **opts)
        batch = {"language": LanguageContext(cfg), "modules": torch.nn.ModuleDict({BRIDGE_MODULE: bridge})}
        model.zero_grad(set_to_none=True)
        color_bridge_loss(batch, model, 10).backward()
        g = model.params["means"].grad
        return torch.zeros_like(model.params["means"]) if g is None else g.clone()

    full = means_grad(bridge_position_scale=1.0)
    assert torch.allclose(means_grad(bridge_position_scale=0.01), 0.01 * full, rtol=1e-4, atol=1e-9)
    assert float(means_grad(bridge_position_grad=False).abs().sum()) == 0.0
    assert float(means_grad(bridge_start=100).abs().sum()) == 0.0


def test_sigma_weights_move_toward_the_task_losses():
    """Toy imbalance: a large and a small task loss. Learned log sigma^2 rises for the large one (its weight
    1/sigma^2 falls) and falls for the small one; at the optimum sigma^2 equals the loss."""
    weights = HomoscedasticWeights(2)
    opt = torch.optim.Adam(weights.parameters(), lr=0.05)
    big, small = torch.tensor(4.0), torch.tensor(0.05)
    for _ in range(400):
        opt.zero_grad()
        weights(big, small).backward()
        opt.step()
    s2 = weights.sigma2
    assert float(s2[0]) > 1.0 > float(s2[1])
    assert float(s2[0]) == pytest.approx(4.0, rel=0.1) and float(s2[1]) == pytest.approx(0.05, rel=0.1)


def test_registered_terms_on_a_fake_render():
    model = _surfels(n=12)
    cfg = LanguageConfig(dim=4, alternate_period=0)
    ctx = LanguageContext(cfg, latent_slice=slice(0, 4), eps_channel=4)
    modules = torch.nn.ModuleDict({BRIDGE_MODULE: BridgeMLP(4, n_freqs=2, width=8, depth=2),
                                   SIGMA_MODULE: HomoscedasticWeights(2)})
    H, W = 5, 6
    feats = torch.rand(H, W, 5, requires_grad=True)
    rgb = torch.rand(H, W, 3, requires_grad=True)
    out = RenderOutput(rgb=rgb, features=feats)
    valid = torch.ones(H, W, 1, dtype=torch.bool)
    valid[0] = False
    batch = {"image": torch.rand(H, W, 3), "lang_target": torch.rand(H, W, 4), "lang_valid": valid,
             "language": ctx, "modules": modules}
    terms = resolve_losses({"ppgs": 1.0})
    res = compute_losses(terms, out, batch, model, step=3, max_steps=10)
    assert torch.isfinite(res.total)
    res.total.backward()
    assert float(feats.grad[1:].abs().sum()) > 0 and float(feats.grad[0, :, :4].abs().sum()) == 0  # invalid row
    assert float(feats.grad[..., 4].abs().sum()) > 0  # the rendered uncertainty channel is trained
    assert modules[SIGMA_MODULE].log_vars.grad is not None
    assert set(ctx.last_terms) >= {"l1", "l_r", "l_c", "l_f", "sigma2_rec", "sigma2_rf"}
    for name in ("lang_feature", "bridge_color", "bridge_feature"):
        value = compute_losses(resolve_losses({name: 1.0}), out, batch, model, 0, 10).total
        assert torch.isfinite(value) and value.dim() == 0
