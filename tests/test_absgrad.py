"""rasterize(..., track_means2d=True, absgrad=True): out.means2d.absgrad after backward is, per Gaussian, the sum
over pixels of each pixel's |dL/dmeans2d| (AbsGS), checked against renders that differentiate one pixel at a time.
test_raster_gpu_kernels_on_cpu.py runs this file with the GPU adjoints too (per-warp, per-block, deterministic)."""
import pytest
import torch

from random_scenes import random_scene
from raster_helpers import DEVICE
from warpgs import rasterize

OUTPUTS = ("rgb", "alpha", "depth")


def scene_tensors(seed, width=14, height=10):
    s = random_scene(n=24, width=width, height=height, seed=seed)
    return {k: (v.float().to(DEVICE) if isinstance(v, torch.Tensor) else v) for k, v in s.items()}


def render(s, viewmat=None, K=None, absgrad=True):
    return rasterize(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"],
                     s["viewmat"] if viewmat is None else viewmat, s["K"] if K is None else K, s["width"], s["height"],
                     outputs=OUTPUTS, track_means2d=True, absgrad=absgrad,
                     background=torch.tensor([0.2, 0.5, 0.1], device=DEVICE))


def weighted(out, w):
    return (out.rgb * w[..., :3]).sum() + (out.alpha * w[..., 3:4]).sum() + (out.depth * w[..., 4:5]).sum()


@pytest.mark.parametrize("seed", [0, 1])
def test_absgrad_is_the_sum_of_each_pixels_absolute_gradient(seed):
    s = scene_tensors(seed)
    H, W = s["height"], s["width"]
    w = torch.randn(H, W, 5, generator=torch.Generator().manual_seed(seed), dtype=torch.float32).to(DEVICE)
    out = render(s)
    weighted(out, w).backward()
    got, grad = out.means2d.absgrad.cpu(), out.means2d.grad.cpu()

    reference = torch.zeros_like(got)
    for y in range(H):
        for x in range(W):
            one = torch.zeros_like(w)
            one[y, x] = w[y, x]
            o = render(s, absgrad=False)
            weighted(o, one).backward()
            reference += o.means2d.grad.cpu().abs()
    assert reference.abs().max() > 0
    torch.testing.assert_close(got, reference, rtol=1e-4, atol=1e-6 * float(reference.abs().max()))
    # the triangle inequality, strict where pixels disagree in sign
    assert (got >= grad.abs() - 1e-6 * float(got.abs().max())).all()
    assert (got > grad.abs() * 1.01 + 1e-9).any()


def test_a_batch_of_cameras_gives_each_its_own_absgrad():
    from random_scenes import look_at

    s = scene_tensors(2)
    views = torch.stack([s["viewmat"], look_at((1.0, 0.0, -4.0), (0.0, 0.0, 0.0)).float().to(DEVICE)])
    Ks = torch.stack([s["K"], s["K"]])
    w = torch.randn(2, s["height"], s["width"], 5, generator=torch.Generator().manual_seed(5)).to(DEVICE)
    batch = render(s, views, Ks)
    weighted(batch, w).backward()
    assert batch.means2d.absgrad.shape == (2, 24, 2)
    for b in range(2):
        single = render(s, views[b], Ks[b])
        weighted(single, w[b]).backward()
        torch.testing.assert_close(batch.means2d.absgrad[b], single.means2d.absgrad, rtol=1e-5, atol=1e-7)


def test_absgrad_needs_track_means2d():
    s = scene_tensors(0)
    with pytest.raises(ValueError, match="absgrad: needs track_means2d"):
        rasterize(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], s["viewmat"], s["K"], s["width"],
                  s["height"], absgrad=True)


def test_training_with_strategy_absgrad_densifies_from_the_absolute_sums(tmp_path, monkeypatch):
    """strategy.absgrad: the densification statistic each view adds is the render's out.means2d.absgrad (not its
    .grad); surfels are refused by name."""
    from train_fixtures import quick_overrides
    from warpgs.train import step as training_step
    from warpgs.train.trainer import Trainer

    seen = []
    real = training_step.view_pass

    def spy(trainer, view, step, **kw):
        p = real(trainer, view, step, **kw)
        if p.grad2d is not None:
            seen.append(p.grad2d.min().item() >= 0.0)  # sums of absolute values only
        return p

    monkeypatch.setattr(training_step, "view_pass", spy)
    t = Trainer(None, overrides=quick_overrides(tmp_path / "abs", steps=30, **{"strategy.absgrad": "true",
                                                                                 "strategy.grad_threshold": 0.0008}),
                quiet=True)
    start = t.model.num_primitives
    t.fit()
    assert seen and all(seen)
    assert t.model.num_primitives != start  # the strategy acted on them
    with pytest.raises(ValueError, match="strategy.absgrad: 3D Gaussians"):
        Trainer(None, overrides=quick_overrides(tmp_path / "s", steps=2, **{"strategy.absgrad": "true",
                                                                            "model.kind": "surfels"}), quiet=True)
