"""The relative-depth judgement, AbsRel and the depth evaluation helper on constructed cases."""
import math
from types import SimpleNamespace

import pytest
import torch

from warpgs.metrics.depth import abs_rel, depth_order_accuracy, evaluate_depth, sample_pairs


def scene_depth(h=24, w=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = 2.0 + 6.0 * torch.rand(h, w, generator=g)
    d[:4] = float("inf")  # sky rows: never probed
    return d


def test_perfect_depth_scores_one_and_reversed_zero():
    gt = scene_depth()
    assert depth_order_accuracy(gt, gt)["accuracy"] == 1.0
    assert depth_order_accuracy(gt * 3.0 + 1.0, gt)["accuracy"] == 1.0  # any increasing map keeps the order
    rev = depth_order_accuracy(1.0 / gt, gt)
    assert rev["accuracy"] == 0.0 and rev["pairs"] == 2000
    assert depth_order_accuracy(torch.full_like(gt, 3.0), gt)["accuracy"] == 0.5  # ties: chance


def test_pairs_respect_the_relative_margin_and_validity():
    gt = scene_depth()
    valid = torch.isfinite(gt)
    pairs = sample_pairs(gt, valid, 500, margin=0.2, generator=torch.Generator().manual_seed(1))
    assert len(pairs) == 500
    a, b = gt.reshape(-1)[pairs[:, 0]], gt.reshape(-1)[pairs[:, 1]]
    assert bool(torch.isfinite(a).all() and torch.isfinite(b).all())
    assert bool(((a - b).abs() > 0.2 * torch.minimum(a, b)).all())
    near = sample_pairs(gt, valid, 300, margin=0.05, max_distance=3, generator=torch.Generator().manual_seed(2))
    ya, xa = near[:, 0] // 32, near[:, 0] % 32
    yb, xb = near[:, 1] // 32, near[:, 1] % 32
    assert len(near) == 300 and bool((((ya - yb) ** 2 + (xa - xb) ** 2) <= 3.5 ** 2).all())


def test_flat_reference_gives_no_pairs_and_nan():
    gt = torch.full((8, 8), 4.0)
    out = depth_order_accuracy(gt, gt)
    assert out["pairs"] == 0 and math.isnan(out["accuracy"])


def test_order_on_a_hand_made_case_with_an_error_and_a_hole():
    # Three columns at depths 2, 4, 8 (pairs inside a column are equal and never drawn, so the three pair types
    # left-middle, left-right, middle-right are equally likely).
    gt = torch.tensor([[2.0, 4.0, 8.0]]).repeat(4, 1)
    # The middle column is rendered in front of the left one (left-middle wrong); the right column is empty
    # (alpha 0), which reads as infinitely far: behind both others, as in the reference (both right).
    pred = torch.tensor([[2.0, 1.0, 0.0]]).repeat(4, 1)
    alpha = torch.tensor([[1.0, 1.0, 0.0]]).repeat(4, 1)
    res = depth_order_accuracy(pred, gt, alpha=alpha, num_pairs=3000, seed=3)
    assert res["pairs"] == 3000 and res["accuracy"] == pytest.approx(2 / 3, abs=0.03)
    # An empty left column reads as behind everything: left-middle and left-right wrong, middle-right right.
    pred2 = torch.tensor([[0.0, 4.0, 8.0]]).repeat(4, 1)
    res2 = depth_order_accuracy(pred2, gt, num_pairs=3000, seed=3)
    assert res2["accuracy"] == pytest.approx(1 / 3, abs=0.03)


def test_abs_rel_by_hand_with_coverage():
    gt = torch.tensor([[2.0, 4.0], [float("inf"), 0.0]])  # sky and unknown pixels are not scored
    pred = torch.tensor([[2.2, 3.0], [5.0, 5.0]])
    out = abs_rel(pred, gt)
    assert out["abs_rel"] == pytest.approx((0.1 + 0.25) / 2) and out["coverage"] == 1.0 and out["pixels"] == 2
    half = abs_rel(pred, gt, alpha=torch.tensor([[1.0, 0.1], [1.0, 1.0]]))
    assert half["abs_rel"] == pytest.approx(0.1) and half["coverage"] == 0.5


def test_evaluate_depth_aggregates_views_and_skips_those_without_reference():
    gt = scene_depth(seed=4)[..., None]
    views = [SimpleNamespace(name="a", depth=gt, mask=None), SimpleNamespace(name="b", depth=None),
             SimpleNamespace(name="c", depth=gt, mask=None)]
    renders = {"a": gt.clone(), "c": 1.0 / gt.clone()}
    fn = lambda v: SimpleNamespace(depth=torch.nan_to_num(renders[v.name], posinf=0.0),  # noqa: E731
                                   alpha=torch.ones_like(gt))
    res = evaluate_depth(fn, views, num_primitives=123, num_pairs=400)
    assert res["num_views"] == 2 and res["num_primitives"] == 123 and res["num_pairs"] == 800
    assert res["per_view"]["a"]["depth_order"] == 1.0 and res["per_view"]["c"]["depth_order"] == 0.0
    assert res["depth_order"] == pytest.approx(0.5) and res["per_view"]["a"]["abs_rel"] == 0.0
    with pytest.raises(ValueError, match="reference depth"):
        evaluate_depth(fn, [views[1]])
