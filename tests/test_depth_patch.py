"""The patch-normalised depth term (`depth_patch`, warpgs/losses/depth_patch.py): blind to a positive affine map of
depth within each block, sensitive to local shape, masked like the Marr terms, finite on flat and empty maps, and
its gradient checked against float64 finite differences."""
from types import SimpleNamespace

import pytest
import torch

from warpgs.losses import get_loss, required_outputs, resolve_losses
from warpgs.losses.depth_patch import PATCH, grid_offset, patch_normalised_l1


def _maps(h=24, w=32, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    prior = 0.5 + 0.3 * torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)
    return prior.to(dtype), torch.ones(1, 1, h, w, dtype=torch.bool)


def _blockwise(t, fn, patch=PATCH, offset=(0, 0)):
    """t with fn(block, index) applied to each block of the grid that starts at `offset`."""
    out = t.clone()
    H, W = t.shape[-2:]
    r0, c0 = (offset[0] % patch) - patch, (offset[1] % patch) - patch
    k = 0
    for r in range(r0, H, patch):
        for c in range(c0, W, patch):
            rs, cs = slice(max(r, 0), min(r + patch, H)), slice(max(c, 0), min(c + patch, W))
            if rs.start < rs.stop and cs.start < cs.stop:
                out[..., rs, cs] = fn(t[..., rs, cs], k)
                k += 1
    return out


@pytest.mark.parametrize("offset", [(0, 0), (3, 5)])
def test_a_positive_affine_map_per_block_costs_nothing(offset):
    prior, mask = _maps()
    pred = _blockwise(prior, lambda b, k: (0.5 + 0.1 * k) * b + 0.02 * k, offset=offset)
    assert float(patch_normalised_l1(pred, prior, mask, offset=offset)) == pytest.approx(0.0, abs=1e-4)
    # the same map over the whole image is not free for the global term it stands beside, but is free here
    assert float(patch_normalised_l1(3.0 * prior + 1.0, prior, mask, offset=offset)) == pytest.approx(0.0, abs=1e-4)


def test_a_change_of_local_shape_costs_and_a_flipped_block_costs_most():
    prior, mask = _maps()
    noisy = prior + 0.05 * torch.randn(prior.shape, generator=torch.Generator().manual_seed(1))
    flipped = _blockwise(prior, lambda b, k: -b + 2 * b.mean())  # each block upside down: correlation -1
    small = float(patch_normalised_l1(noisy, prior, mask))
    large = float(patch_normalised_l1(flipped, prior, mask))
    assert 0.05 < small < large


def test_masked_pixels_and_blocks_with_a_flat_prior_are_left_out():
    prior, mask = _maps()
    pred = prior + 0.1 * torch.randn(prior.shape, generator=torch.Generator().manual_seed(2))
    mask[..., :, :5] = False
    changed = pred.clone()
    changed[..., :, :5] = 7.0  # invalid pixels: any value
    assert float(patch_normalised_l1(pred, prior, mask)) == pytest.approx(float(patch_normalised_l1(changed, prior,
                                                                                                    mask)))
    flat = prior.clone()
    flat[..., :PATCH, :PATCH] = 0.6  # one block of constant prior: normalising it would amplify noise
    base = patch_normalised_l1(pred, flat, mask)
    again = pred.clone()
    again[..., :PATCH, :PATCH] += torch.randn(PATCH, PATCH, generator=torch.Generator().manual_seed(3))
    assert float(patch_normalised_l1(again, flat, mask)) == pytest.approx(float(base))


def test_flat_and_empty_maps_give_finite_values_and_gradients():
    prior, mask = _maps(h=16, w=16)
    for pred, m in ((torch.full_like(prior, 0.4), mask), (prior.clone(), torch.zeros_like(mask))):
        pred.requires_grad_(True)
        loss = patch_normalised_l1(pred, prior, m)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(pred.grad).all()


def test_gradient_matches_float64_finite_differences():
    prior, mask = _maps(h=12, w=12, dtype=torch.float64)
    mask[..., 0, :3] = False
    weight = torch.rand(prior.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    pred = (prior + 0.05 * torch.randn(prior.shape, generator=torch.Generator().manual_seed(5),
                                       dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: patch_normalised_l1(p, prior, mask, weight, patch=4, offset=(1, 2)),
                                    (pred,), eps=1e-6, atol=1e-6)


def test_registered_off_by_default_and_reads_alpha_and_inverse_depth():
    term = get_loss("depth_patch")
    assert set(term.outputs) == {"alpha", "inv_depth"}
    assert "depth_patch" not in resolve_losses(None)  # only where a config lists it
    assert set(required_outputs(resolve_losses({"depth_patch": 1.0}))) == {"alpha", "inv_depth"}
    prior, _ = _maps()
    out = SimpleNamespace(alpha=torch.ones(24, 32, 1), inv_depth=(2.0 * prior + 0.1)[0].permute(1, 2, 0))
    batch = {"inv_depth_prior": prior[0].permute(1, 2, 0), "inv_depth_valid": torch.ones(24, 32, 1, dtype=torch.bool)}
    assert float(term.fn(out, batch, None, 7)) == pytest.approx(0.0, abs=1e-4)
    assert grid_offset(0) == (0, 0) and len({grid_offset(s) for s in range(PATCH)}) == PATCH
