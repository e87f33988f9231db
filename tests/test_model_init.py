"""GaussianModel / SurfelModel: initialisation values, activations, SH bands, extras, checkpoints."""
import math

import pytest
import torch

import warpgs.model.gaussians as gs
from warpgs.model.gaussians import SH_C0, GaussianModel, SurfelModel, knn_scale, rgb_to_sh0, sh0_to_rgb


def grid(n=3, spacing=0.5, offset=0.0):
    r = torch.arange(n, dtype=torch.float32) * spacing + offset
    return torch.cartesian_prod(r, r, r)


def test_from_points_values():
    pts = grid()  # every grid point has at least 3 neighbours at exactly 0.5
    rgb = torch.rand(len(pts), 3, generator=torch.Generator().manual_seed(1))
    m = GaussianModel.from_points(pts, rgb, sh_degree=3)
    n = len(pts)
    assert m.num_primitives == n and m.max_sh_degree == 3 and m.active_sh_degree == 0
    assert m.log_scales.shape == (n, 3) and m.quats.shape == (n, 4) and m.logit_opacities.shape == (n,)
    assert m.sh0.shape == (n, 1, 3) and m.shN.shape == (n, 15, 3)
    torch.testing.assert_close(m.scales, torch.full((n, 3), 0.5))
    torch.testing.assert_close(m.opacities, torch.full((n,), 0.1))
    torch.testing.assert_close(m.sh0[:, 0], (rgb - 0.5) / SH_C0)
    torch.testing.assert_close(sh0_to_rgb(m.sh0[:, 0]), rgb)
    assert torch.equal(m.shN, torch.zeros(n, 15, 3))
    assert torch.equal(m.quats, torch.tensor([1.0, 0, 0, 0]).expand(n, 4))
    assert torch.equal(m.means, pts)


def test_uint8_and_missing_colours():
    pts = grid(2)
    m = GaussianModel.from_points(pts, torch.full((8, 3), 255, dtype=torch.uint8), sh_degree=0)
    torch.testing.assert_close(sh0_to_rgb(m.sh0), torch.ones(8, 1, 3))
    assert m.shN.shape == (8, 0, 3)
    grey = GaussianModel.from_points(pts)
    assert torch.equal(grey.sh0, torch.zeros(8, 1, 3))


def brute_knn_scale(p, k):
    d = torch.cdist(p.double(), p.double(), compute_mode="donot_use_mm_for_euclid_dist")
    d.fill_diagonal_(float("inf"))
    return (d.topk(k, largest=False).values ** 2).mean(1).clamp_min(1e-7).sqrt().float()


def test_knn_scale_matches_brute_force():
    p = torch.randn(200, 3, generator=torch.Generator().manual_seed(0))
    p[7] = p[3]  # a duplicate: its nearest distance is 0
    torch.testing.assert_close(knn_scale(p, 3), brute_knn_scale(p, 3))
    assert knn_scale(p, 3)[7] < knn_scale(p, 3)[0] + 10  # finite
    assert torch.isfinite(knn_scale(torch.zeros(5, 3)).log()).all()  # all coincident: floored, finite log


def test_knn_scale_precise_far_from_origin():
    # Spacing 1e-3 around 100: the |x|^2 + |y|^2 - 2xy shortcut would lose everything in float32.
    s = knn_scale(grid(3, 1e-3, 100.0))
    torch.testing.assert_close(s, torch.full_like(s, 1e-3), rtol=2e-2, atol=0)


def test_knn_scale_few_points():
    torch.testing.assert_close(knn_scale(torch.zeros(1, 3)), torch.tensor([0.01]))
    two = knn_scale(torch.tensor([[0.0, 0, 0], [2.0, 0, 0]]))
    torch.testing.assert_close(two, torch.tensor([2.0, 2.0]))


def test_random_init_in_box_and_seeded():
    lo, hi = [-1.0, 0.0, 2.0], [1.0, 0.5, 3.0]
    a = GaussianModel.random_init(300, lo, hi, generator=torch.Generator().manual_seed(3))
    b = GaussianModel.random_init(300, lo, hi, generator=torch.Generator().manual_seed(3))
    assert a.num_primitives == 300
    assert (a.means >= torch.tensor(lo)).all() and (a.means <= torch.tensor(hi)).all()
    assert torch.equal(a.means, b.means) and torch.equal(a.sh0, b.sh0)
    rgb = sh0_to_rgb(a.sh0)
    assert rgb.min() >= 0 and rgb.max() <= 1 and rgb.std() > 0.1  # random colours, not grey
    with pytest.raises(ValueError, match="bbox"):
        GaussianModel.random_init(10, [0, 0, 0], [1, 0, 1])
    with pytest.raises(ValueError, match="num_points"):
        GaussianModel.random_init(0, lo, hi)


def test_max_points_subsamples():
    m = GaussianModel.from_points(grid(4), max_points=10, generator=torch.Generator().manual_seed(0))
    assert m.num_primitives == 10
    assert len({tuple(r) for r in m.means.tolist()}) == 10  # distinct points, a subset


def test_surfels():
    s = SurfelModel.from_points(grid(), generator=torch.Generator().manual_seed(0))
    assert s.log_scales.shape == (27, 2) and s.render_inputs()["scales"].shape == (27, 2)
    torch.testing.assert_close(s.quats.norm(dim=1), torch.ones(27))
    assert s.quats.std(0).min() > 0.2  # random orientations, not all identity
    torch.testing.assert_close(s.scales, torch.full((27, 2), 0.5))


def test_sh_bands_and_render_inputs():
    m = GaussianModel.from_points(grid(2), sh_degree=3)
    assert m.sh_coeffs().shape == (8, 1, 3)
    m.active_sh_degree = 1
    assert m.sh_coeffs().shape == (8, 4, 3)
    m.active_sh_degree = 3
    assert m.sh_coeffs().shape == (8, 16, 3)
    with pytest.raises(ValueError, match="active_sh_degree"):
        m.active_sh_degree = 4
    inputs = m.render_inputs()
    assert inputs["sh_degree"] == 3 and inputs["opacities"].shape == (8,)
    loss = sum(v.sum() for k, v in inputs.items() if k != "sh_degree")
    loss.backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in m.params.values())


def test_extras():
    m = GaussianModel.from_points(grid(2))
    m.add_extra("language", torch.zeros(8, 8))
    assert m.extra_names == ["language"] and m.params["language"].requires_grad
    with pytest.raises(ValueError, match="language"):
        m.add_extra("language", torch.zeros(8, 8))
    with pytest.raises(ValueError, match="rows"):
        m.add_extra("other", torch.zeros(7, 2))
    with pytest.raises(ValueError, match="name"):
        m.add_extra("scale", torch.zeros(8, 2))  # would collide with scale_0.. in PLY files
    with pytest.raises(ValueError, match="other"):
        m.add_extra("other", torch.zeros(8))  # extras are [N, C]


@pytest.mark.parametrize("bad,match", [
    (dict(points=torch.zeros(0, 3)), "points"),
    (dict(points=torch.zeros(4, 2)), "points"),
    (dict(points=torch.full((4, 3), float("nan"))), "points"),
    (dict(colors=torch.zeros(3, 3)), "colors"),
    (dict(sh_degree=4), "sh_degree"),
    (dict(opacity=1.0), "opacity"),
])
def test_from_points_errors(bad, match):
    kwargs = dict(points=grid(2), colors=None)
    kwargs.update(bad)
    with pytest.raises(ValueError, match=match):
        GaussianModel.from_points(kwargs.pop("points"), kwargs.pop("colors"), **kwargs)


def test_constructor_checks_shapes():
    m = GaussianModel.from_points(grid(2))
    args = [m.params[n].detach() for n in gs.CORE_PARAMS]
    with pytest.raises(ValueError, match="shN"):
        GaussianModel(*args[:5], torch.zeros(8, 5, 3))  # 5 rest coefficients is no SH degree
    with pytest.raises(ValueError, match="quats"):
        GaussianModel(args[0], args[1], torch.zeros(7, 4), *args[3:])
    with pytest.raises(ValueError, match="log_scales"):
        SurfelModel(*args)  # surfels need 2 scales


def test_to_dict_round_trip_any_size():
    s = SurfelModel.from_points(grid(2), generator=torch.Generator().manual_seed(0))
    s.add_extra("uncertainty", torch.rand(8, 1))
    s.active_sh_degree = 2
    back = GaussianModel.from_dict(s.to_dict())
    assert type(back) is SurfelModel and back.active_sh_degree == 2 and back.extra_names == ["uncertainty"]
    assert all(torch.equal(s.params[n], back.params[n]) for n in s.params)
    with pytest.raises(ValueError, match="kind"):
        GaussianModel.from_dict({"kind": "blobs", "params": {}})
    assert math.isclose(float(rgb_to_sh0(torch.tensor(0.5))), 0.0)


def test_model_owns_its_tensors():
    pts = grid(2)
    m = GaussianModel.from_points(pts)
    with torch.no_grad():
        m.params["means"].add_(1.0)  # what an optimizer step does
    assert torch.equal(pts, grid(2))
