"""Sparse-view terms (issue 6): the Marr depth terms and the Gestalt terms against values computed by hand,
their schedule, and weight 0 removing a term and its render outputs."""
import math
from types import SimpleNamespace

import pytest
import torch
from torch.overrides import TorchFunctionMode

from warpgs.losses import compute_losses, get_loss, resolve_losses, required_outputs
from warpgs.losses import gestalt, marr
from warpgs.losses.sobel import sobel_gradient

MARR = ("depth", "depth_grad", "depth_local")
GESTALT = ("opacity", "scale", "count")


def render(inv_depth_hat, alpha=None):
    """A render whose normalised inverse depth inv_depth/alpha is `inv_depth_hat` ([H, W])."""
    d = torch.as_tensor(inv_depth_hat, dtype=torch.float32)[..., None]
    a = torch.ones_like(d) if alpha is None else torch.as_tensor(alpha, dtype=torch.float32)[..., None]
    return SimpleNamespace(rgb=None, alpha=a, depth=None, inv_depth=d * a, features=None)


def batch(prior, valid=None):
    p = torch.as_tensor(prior, dtype=torch.float32)[..., None]
    v = torch.ones_like(p, dtype=torch.bool) if valid is None else torch.as_tensor(valid, dtype=torch.bool)[..., None]
    return {"inv_depth_prior": p, "inv_depth_valid": v}


def value(name, out, b, model=None):
    return float(get_loss(name).fn(out, b, model, 0))


# ----- Marr -------------------------------------------------------------------------------------------------
def test_registered_with_paper_defaults():
    for name in MARR:
        t = get_loss(name)
        assert t.weight == 1.0 and set(t.outputs) == {"alpha", "inv_depth"}
        assert t.schedule(0, 100) == pytest.approx(1.0) and t.schedule(100, 100) == pytest.approx(0.01)
    assert [(n, get_loss(n).weight, get_loss(n).outputs) for n in GESTALT] == [
        ("opacity", 0.05, ()), ("scale", 0.008, ()), ("count", 0.001, ())]


def test_depth_is_mean_abs_error_over_valid_covered_pixels():
    pred = [[0.5, 0.2], [0.3, 0.1]]
    alpha = [[1.0, 0.5], [1.0, 0.05]]  # (1,1) is below alpha_min = 0.1
    prior = [[0.4, 0.25], [0.3, 0.9]]
    valid = [[1, 1], [0, 1]]  # (1,0) has no prior
    # |0.5-0.4| + |0.2-0.25| over 2 pixels
    assert value("depth", render(pred, alpha), batch(prior, valid)) == pytest.approx(0.075, abs=1e-6)


def test_depth_uses_alpha_normalised_accumulated_inverse_depth():
    # inv_depth = Σ w/z = 0.15 with alpha 0.5 -> D̂ = 0.3: equal to the prior, so no loss.
    out = SimpleNamespace(alpha=torch.full((1, 1, 1), 0.5), inv_depth=torch.full((1, 1, 1), 0.15))
    assert value("depth", out, batch([[0.3]])) == pytest.approx(0.0, abs=1e-7)


def test_depth_excludes_nonfinite_and_nonpositive_prior_and_batch_mask():
    b = batch([[float("nan"), 0.0], [0.2, 0.4]], [[1, 1], [1, 1]])
    b["mask"] = torch.tensor([[True], [True], [True], [False]]).reshape(2, 2, 1)
    assert value("depth", render([[9.0, 9.0], [0.5, 9.0]]), b) == pytest.approx(0.3, abs=1e-6)


def test_depth_alpha_threshold_is_configurable():
    out, b = render([[0.5, 0.2]], [[1.0, 0.05]]), batch([[0.4, 0.4]])
    assert value("depth", out, b) == pytest.approx(0.1, abs=1e-6)
    old = marr.SETTINGS.alpha_min
    try:
        marr.configure(alpha_min=0.0)
        assert value("depth", out, b) == pytest.approx(0.15, abs=1e-6)
    finally:
        marr.configure(alpha_min=old)
    with pytest.raises(ValueError, match="unknown setting"):
        marr.configure(alpha=0.2)


def test_depth_grad_on_a_quadratic_ramp():
    # D̂ - D* = c x² along x; the normalised Sobel (central difference, smoothed along y) gives 2 c x exactly at
    # interior pixels x = 1, 2, 3. Pixel (0, 0) has no prior, so pixel (1, 1)'s window is incomplete: 8 pixels
    # count, with |∂x| = 2c (x=1, 2 of them), 4c (3), 6c (3) and ∂y = 0: (4 + 12 + 18) c / 8.
    c = 0.01
    x = torch.arange(5.0)
    diff = (c * x * x).expand(5, 5)
    prior = torch.full((5, 5), 0.3)
    prior[0, 0] = float("nan")
    valid = torch.ones(5, 5, dtype=torch.bool)
    valid[0, 0] = False
    got = value("depth_grad", render(0.3 + diff), batch(prior, valid))
    assert got == pytest.approx(34 * c / 8, rel=1e-4)


def test_depth_grad_sums_both_components_and_ignores_an_offset():
    y, x = torch.meshgrid(torch.arange(4.0), torch.arange(6.0), indexing="ij")
    pred = 0.2 + 0.02 * x  # slope +0.02 in x
    prior = 0.1 + 0.01 * y  # slope +0.01 in y, and a different offset
    # every interior pixel: |0.02 - 0| + |0 - 0.01|
    assert value("depth_grad", render(pred), batch(prior)) == pytest.approx(0.03, rel=1e-4)


def test_depth_local_mean_and_variance_of_a_3x3_window():
    pred = 0.01 * torch.arange(1.0, 10.0).reshape(3, 3)  # mean 0.05, population variance 1e-4 * 60 / 9
    prior = torch.full((3, 3), 0.04)  # mean 0.04, variance 0
    got = value("depth_local", render(pred), batch(prior))
    assert got == pytest.approx(0.01 + 1e-4 * 60 / 9, rel=1e-4)


def test_depth_local_averages_over_complete_windows_only():
    # 3x4: two complete windows (centres (1,1) and (1,2)). Column 3 of the prior is invalid, which removes the
    # window at (1,2): only (1,1) counts, whose window is columns 0..2.
    pred = torch.tensor([[0.1, 0.2, 0.3, 5.0], [0.1, 0.2, 0.3, 5.0], [0.1, 0.2, 0.3, 5.0]])
    prior = torch.full((3, 4), 0.2)
    valid = torch.ones(3, 4, dtype=torch.bool)
    valid[:, 3] = False
    var = ((0.1 - 0.2) ** 2 + 0 + (0.3 - 0.2) ** 2) / 3  # per row, same for the window
    got = value("depth_local", render(pred), batch(prior, valid))
    assert got == pytest.approx(0.0 + var, rel=1e-4)


def test_marr_terms_on_empty_mask_are_zero_and_finite():
    out, b = render(torch.rand(4, 4)), batch(torch.rand(4, 4), torch.zeros(4, 4))
    for name in MARR:
        assert value(name, out, b) == 0.0


def test_marr_terms_accept_batched_maps():
    pred, prior = torch.rand(2, 5, 6), torch.rand(2, 5, 6)
    out = SimpleNamespace(alpha=torch.ones(2, 5, 6, 1), inv_depth=pred[..., None])
    b = {"inv_depth_prior": prior[..., None], "inv_depth_valid": torch.ones(2, 5, 6, 1, dtype=torch.bool)}
    assert value("depth", out, b) == pytest.approx(float((pred - prior).abs().mean()), rel=1e-5)
    for name in ("depth_grad", "depth_local"):
        assert math.isfinite(value(name, out, b))


class _HostTensors(TorchFunctionMode):
    """Counts tensors made from host data (torch.tensor / as_tensor): on a GPU each is a copy torch ends with a
    stream synchronisation."""

    def __init__(self):
        super().__init__()
        self.made = 0

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func in (torch.tensor, torch.as_tensor):
            self.made += 1
        return func(*args, **(kwargs or {}))


def test_sobel_gradient_is_kornias_bit_for_bit():
    from kornia.filters import spatial_gradient
    torch.manual_seed(0)
    for shape, dtype in (((2, 3, 7, 9), torch.float32), ((1, 1, 5, 4), torch.float32), ((1, 2, 6, 6), torch.float64)):
        x = torch.randn(shape, dtype=dtype)
        assert torch.equal(sobel_gradient(x), spatial_gradient(x, mode="sobel", order=1, normalized=True))


def test_marr_terms_make_no_tensor_from_host_data_once_warm():
    # depth_grad's Sobel kernel came from a Python list on every call (kornia), a host sync a step on a GPU
    torch.manual_seed(0)
    out = render(torch.rand(6, 7) + 0.1)
    out.inv_depth.requires_grad_(True)
    b = batch(torch.rand(6, 7) + 0.1)
    b["inv_depth_confidence"] = torch.rand(6, 7, 1)
    for name in MARR:
        get_loss(name).fn(out, b, None, 0).backward()  # warm: caches made once
        with _HostTensors() as mode:
            get_loss(name).fn(out, b, None, 0).backward()
        assert mode.made == 0, name


def test_missing_prior_names_the_fix():
    with pytest.raises(ValueError, match="inv_depth_prior.*weight 0"):
        value("depth", render([[0.1]]), {"image": torch.zeros(1, 1, 3)})


# ----- Gestalt ------------------------------------------------------------------------------------------------
def test_opacity_scale_count_by_hand():
    model = SimpleNamespace(opacities=torch.tensor([0.2, 0.4, 0.9]),
                            scales=torch.tensor([[3.0, 4.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]))
    assert value("opacity", None, None, model) == pytest.approx(0.5)
    assert value("scale", None, None, model) == pytest.approx((5.0 + 1.0 + 0.0) / 3)
    tau, T = gestalt.SETTINGS.count_tau, gestalt.SETTINGS.count_temperature
    expected = math.log(sum(1 / (1 + math.exp(-(a - tau) / T)) for a in (0.2, 0.4, 0.9)) + 1e-6)
    assert value("count", None, None, model) == pytest.approx(expected, rel=1e-6)


def test_count_is_log_n_for_opaque_primitives_and_ignores_faint_ones():
    assert (gestalt.SETTINGS.count_tau, gestalt.SETTINGS.count_temperature) == (0.005, 0.05)
    opaque = torch.full((1000,), 0.99)
    assert value("count", None, None, SimpleNamespace(opacities=opaque)) == pytest.approx(math.log(1000), rel=1e-5)
    faint = torch.cat([opaque, torch.full((500,), 1e-4)])
    # each faint primitive still counts sigmoid(-0.0049 / 0.05) ~ 0.48: the soft count is soft below tau too
    s = 1000 / (1 + math.exp(-(0.99 - 0.005) / 0.05)) + 500 / (1 + math.exp((0.005 - 1e-4) / 0.05))
    assert value("count", None, None, SimpleNamespace(opacities=faint)) == pytest.approx(math.log(s), rel=1e-5)
    with pytest.raises(ValueError):
        gestalt.configure(count_temperature=0)


def test_count_gradient_pushes_opacities_down_and_is_largest_near_tau():
    logit = torch.tensor([-5.3, 0.0, 3.0], requires_grad=True)  # opacities ~0.005, 0.5, 0.95
    model = SimpleNamespace(opacities=torch.sigmoid(logit))
    get_loss("count").fn(None, None, model, 0).backward()
    g = logit.grad
    assert bool((g >= 0).all())  # descent never raises an opacity
    assert float(g[0]) > float(g[1]) > 0  # and acts hardest on the primitives near the threshold


def test_gestalt_on_empty_model_is_finite():
    model = SimpleNamespace(opacities=torch.zeros(0), scales=torch.zeros(0, 3))
    for name in GESTALT:
        assert math.isfinite(value(name, None, None, model))


# ----- schedule and ablation by weight 0 -------------------------------------------------------------------------
def test_exponential_schedule_hits_1_and_0_01_at_its_ends():
    terms = {t.name: t for t in resolve_losses({"depth": None, "depth_grad": {"weight": 2.0}})}
    for steps in (10, 30_000):
        assert terms["depth"].weight_at(0, steps) == pytest.approx(1.0)
        assert terms["depth"].weight_at(steps, steps) == pytest.approx(0.01)
        assert terms["depth"].weight_at(steps // 2, steps) == pytest.approx(0.1)  # log-linear: geometric midpoint
        assert terms["depth"].weight_at(10 * steps, steps) == pytest.approx(0.01)  # held after the end
    assert terms["depth_grad"].weight_at(0, 100) == pytest.approx(2.0)  # the weight scales the schedule
    assert terms["depth_grad"].weight_at(100, 100) == pytest.approx(0.02)
    # the schedule is generic: any loss can take it
    l1 = resolve_losses({"l1": {"weight": 0.8, "schedule": ["exp", 1, 0.01]}})[0]
    assert l1.weight_at(0, 50) == pytest.approx(0.8) and l1.weight_at(50, 50) == pytest.approx(0.008)


FULL = {"l1": 0.8, "dssim": 0.2, "depth": None, "depth_grad": None, "depth_local": None,
        "opacity": None, "scale": None, "count": None}


def test_weight_zero_removes_each_term_and_the_depth_outputs_go_with_the_last_depth_term():
    assert required_outputs(resolve_losses(FULL)) == ("rgb", "alpha", "inv_depth")
    for name in MARR + GESTALT:
        terms = resolve_losses({**FULL, name: 0})
        assert name not in [t.name for t in terms]
        assert required_outputs(terms) == ("rgb", "alpha", "inv_depth")  # other depth terms still need them
    no_depth = resolve_losses({**FULL, **{n: 0 for n in MARR}})
    assert required_outputs(no_depth) == ("rgb",)
    only_grad = resolve_losses({"l1": 1.0, "depth_grad": {"weight": 1.0}})
    assert required_outputs(only_grad) == ("rgb", "alpha", "inv_depth")


def test_compute_losses_weighs_terms_by_schedule():
    out = render(torch.full((4, 4), 0.3))
    out.rgb = torch.zeros(4, 4, 3)
    b = {**batch(torch.full((4, 4), 0.2)), "image": torch.zeros(4, 4, 3)}
    model = SimpleNamespace(opacities=torch.tensor([0.5]), scales=torch.ones(1, 3))
    terms = resolve_losses(FULL)
    first = compute_losses(terms, out, b, model, 0, 100)
    last = compute_losses(terms, out, b, model, 100, 100)
    assert first.weights["depth"] == pytest.approx(1.0) and last.weights["depth"] == pytest.approx(0.01)
    assert first.values["depth"] == pytest.approx(0.1, abs=1e-6)
    assert first.weights["opacity"] == last.weights["opacity"] == 0.05
    gest = 0.05 * 0.5 + 0.008 * math.sqrt(3) + 0.001 * float(first.values["count"])
    # L1/D-SSIM are 0; depth and depth_local (window means differ by the offset) 0.1 each; depth_grad 0
    assert first.values["depth_local"] == pytest.approx(0.1, abs=1e-6) and abs(float(first.values["depth_grad"])) < 1e-6
    assert float(first.total) == pytest.approx(0.2 + gest, abs=1e-5)
    assert float(last.total) == pytest.approx(0.002 + gest, abs=1e-5)


def test_sobel_kernel_first_made_under_inference_mode_serves_differentiated_calls():
    from warpgs.losses.sobel import sobel_kernel
    sobel_kernel.cache_clear()  # the kernel is made by the first call, here an evaluation's
    with torch.inference_mode():
        sobel_gradient(torch.rand(1, 1, 5, 6))
    x = torch.rand(1, 1, 5, 6, requires_grad=True)
    sobel_gradient(x).abs().sum().backward()  # an inference-tensor kernel could not be saved for backward
    assert x.grad is not None and torch.isfinite(x.grad).all()
