"""Sparse-view terms through a real (small) rasterize call: gradients reach means, scales and opacities."""
import math

import pytest
import torch

from raster_helpers import DEVICE
from warpgs.model.gaussians import GaussianModel
from warpgs.losses import get_loss
from warpgs.model.rendering import render_model

W, H = 32, 24
K = torch.tensor([[30.0, 0.0, W / 2], [0.0, 30.0, H / 2], [0.0, 0.0, 1.0]])
PARAMS = ("means", "log_scales", "logit_opacities")


def small_model(seed=0, n=40):
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n, 2, generator=g) - 0.5) * torch.tensor([1.6, 1.2])
    z = 2.0 + 2.0 * torch.rand(n, 1, generator=g)
    pts = torch.cat([xy * z / 2.0, z], 1)
    model = GaussianModel.from_points(pts, torch.rand(n, 3, generator=g), sh_degree=0, opacity=0.6, generator=g)
    return model.to(DEVICE)


def render(model):
    return render_model(model, torch.eye(4, device=DEVICE), K.to(DEVICE), W, H,
                        outputs=("rgb", "alpha", "inv_depth"))


def prior_batch(model, factor=1.15):
    """A prior that disagrees with the current render: its inverse depth scaled and tilted, valid where covered."""
    with torch.no_grad():
        out = render(model)
        d = out.inv_depth / out.alpha.clamp_min(1e-6)
        tilt = torch.linspace(0.9, 1.1, W, device=d.device)[None, :, None]
        prior = d * factor * tilt
        valid = out.alpha > 0.3
    return {"inv_depth_prior": prior, "inv_depth_valid": valid}


@pytest.mark.parametrize("name", ["depth", "depth_grad", "depth_local"])
def test_marr_gradients_reach_means_scales_opacities(name):
    model = small_model()
    b = prior_batch(model)
    assert int(b["inv_depth_valid"].sum()) > 50
    loss = get_loss(name).fn(render(model), b, model, 0)
    assert float(loss.detach()) > 0
    loss.backward()
    for p in PARAMS:
        g = model.params[p].grad
        assert g is not None and bool(torch.isfinite(g).all()), p
        assert float(g.abs().sum()) > 0, f"{name}: no gradient reaches {p}"


def test_gestalt_gradients_reach_their_parameters():
    model = small_model()
    for name, param in (("opacity", "logit_opacities"), ("scale", "log_scales"), ("count", "logit_opacities")):
        model.zero_grad(set_to_none=True)
        get_loss(name).fn(None, None, model, 0).backward()
        g = model.params[param].grad
        assert g is not None and bool(torch.isfinite(g).all()) and float(g.abs().sum()) > 0, name
        assert bool((g >= 0).all()), f"{name}: descent should only shrink"  # opacity/scale/count only push down


def test_depth_term_alone_moves_the_geometry_towards_the_prior():
    """A few Adam steps on the depth term (means only) reduce it: the gradients point the right way."""
    torch.manual_seed(0)
    model = small_model(seed=1)
    b = prior_batch(model, factor=1.2)  # the prior says: everything 20% closer
    opt = torch.optim.Adam([model.params["means"]], lr=0.01)
    term = get_loss("depth").fn
    first = float(term(render(model), b, model, 0).detach())
    for _ in range(15):
        opt.zero_grad()
        term(render(model), b, model, 0).backward()
        opt.step()
    last = float(term(render(model), b, model, 0).detach())
    assert math.isfinite(last) and last < 0.7 * first
