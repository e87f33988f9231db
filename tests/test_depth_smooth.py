"""The good-continuation term (`depth_smooth`, warpgs/losses/continuity.py): planes at any slant and any depth scale
cost nothing, curvature costs, image edges and confident prior pixels are spared, uncovered windows are left out,
values and gradients are finite on flat and empty maps, and the gradient matches float64 finite differences."""
from types import SimpleNamespace

import pytest
import torch

from warpgs.losses import get_loss, required_outputs, resolve_losses
from warpgs.losses.continuity import curvature_l1, edge_weight, silence


def _grid(h=16, w=20, dtype=torch.float64):
    y, x = torch.meshgrid(torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij")
    return y[None, None], x[None, None]


def test_planes_cost_nothing_at_any_slant_or_scale_and_curvature_costs():
    y, x = _grid()
    mask = torch.ones_like(x, dtype=torch.bool)
    plane = 0.5 + 0.02 * x - 0.01 * y
    assert float(curvature_l1(plane, mask)) == pytest.approx(0.0, abs=1e-9)
    bowl = 0.5 + 0.001 * ((x - 10) ** 2 + (y - 8) ** 2)
    assert float(curvature_l1(bowl, mask)) > 1e-3
    # blind to the scene's units: the depth map over its mean
    assert float(curvature_l1(7.0 * bowl, mask)) == pytest.approx(float(curvature_l1(bowl, mask)), rel=1e-9)


def test_uncovered_windows_are_left_out():
    y, x = _grid()
    mask = torch.ones_like(x, dtype=torch.bool)
    mask[..., :, :6] = False
    plane = 0.5 + 0.02 * x
    wild = plane.clone()
    wild[..., :, :6] = torch.rand(16, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    # the mean that normalises d is taken over the covered pixels only, so it is the same for both
    assert float(curvature_l1(wild, mask)) == pytest.approx(0.0, abs=1e-9)


def test_edges_and_a_confident_prior_spare_a_pixel():
    img = torch.zeros(1, 3, 16, 20)
    img[..., :, 10:] = 1.0  # a vertical edge
    w = edge_weight(img)
    assert float(w[0, 0, 8, 2]) == pytest.approx(1.0) and float(w[0, 0, 8, 10]) < 0.01
    prior = torch.full((16, 20, 1), 0.5)
    valid = torch.ones(16, 20, 1, dtype=torch.bool)
    valid[:4] = False
    conf = torch.full((16, 20, 1), 0.75)
    s = silence({"inv_depth_prior": prior, "inv_depth_valid": valid, "inv_depth_confidence": conf},
                torch.zeros(1, 1, 16, 20))
    assert float(s[0, 0, 0, 0]) == pytest.approx(1.0) and float(s[0, 0, 10, 0]) == pytest.approx(0.25)
    assert float(silence({}, torch.zeros(1, 1, 4, 4)).min()) == 1.0  # no prior: silent everywhere


def test_flat_and_empty_maps_give_finite_values_and_gradients():
    y, x = _grid(dtype=torch.float32)
    for pred, m in ((torch.full_like(x, 0.4), torch.ones_like(x, dtype=torch.bool)),
                    (x.clone(), torch.zeros_like(x, dtype=torch.bool)),
                    (torch.zeros_like(x), torch.ones_like(x, dtype=torch.bool))):
        pred.requires_grad_(True)
        loss = curvature_l1(pred, m)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(pred.grad).all()


def test_gradient_matches_float64_finite_differences():
    y, x = _grid(h=9, w=10)
    mask = torch.ones_like(x, dtype=torch.bool)
    mask[..., 0, :3] = False
    weight = torch.rand(x.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    pred = (0.5 + 0.01 * x + 0.05 * torch.rand(x.shape, generator=torch.Generator().manual_seed(2),
                                               dtype=torch.float64)).requires_grad_(True)
    # the normalising mean is detached (a unit, not something to optimise): checked at a fixed one
    scale = torch.tensor(0.55, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda p: curvature_l1(p, mask, weight, scale), (pred,), eps=1e-6, atol=1e-6)


def test_registered_off_by_default_reads_alpha_and_inverse_depth_and_needs_no_prior():
    term = get_loss("depth_smooth")
    assert set(term.outputs) == {"alpha", "inv_depth"} and term.batch == ()
    assert "depth_smooth" not in resolve_losses(None)
    assert set(required_outputs(resolve_losses({"depth_smooth": 1.0}))) == {"alpha", "inv_depth"}
    y, x = _grid(dtype=torch.float32)
    image = torch.full((16, 20, 3), 0.5)
    out = SimpleNamespace(alpha=torch.ones(16, 20, 1), inv_depth=(0.5 + 0.001 * (x - 10) ** 2)[0].permute(1, 2, 0))
    curved = float(term.fn(out, {"image": image}, None, 0))
    assert curved > 0
    # a confident prior everywhere silences it
    known = {"image": image, "inv_depth_prior": torch.full((16, 20, 1), 0.5),
             "inv_depth_confidence": torch.ones(16, 20, 1)}
    assert float(term.fn(out, known, None, 0)) == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError, match="image"):
        term.fn(out, {"image": torch.zeros(8, 8, 3)}, None, 0)
