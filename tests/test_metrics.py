"""PSNR/SSIM on known inputs; LPIPS only from local files, otherwise None with a reason."""
import sys

import pytest
import torch

import warpgs.metrics.image as metrics
from warpgs.metrics.image import LPIPSMetric, image_metrics, lpips_unavailable_reason, psnr, ssim


def test_psnr_known_values():
    gt = torch.zeros(4, 4, 3)
    assert float(psnr(gt + 0.1, gt)) == pytest.approx(20.0, abs=1e-4)  # MSE 0.01
    pair = torch.stack([gt + 0.1, gt + 0.01]), torch.stack([gt, gt])  # 20 dB and 40 dB -> mean of per-image
    assert float(psnr(*pair)) == pytest.approx(30.0, abs=1e-3)
    assert float(psnr(gt, gt)) == pytest.approx(100.0)  # floored, finite
    assert float(psnr(gt + 25.5, gt, max_val=255.0)) == pytest.approx(20.0, abs=1e-4)


def test_ssim_known_values():
    x = torch.rand(12, 12, 3, generator=torch.Generator().manual_seed(0))
    assert float(ssim(x, x)) == pytest.approx(1.0, abs=1e-6)
    a, b, c1 = 0.3, 0.9, 1e-4
    want = (2 * a * b + c1) / (a * a + b * b + c1)
    f64 = dict(dtype=torch.float64)
    assert float(ssim(torch.full((12, 12, 3), a, **f64), torch.full((12, 12, 3), b, **f64))) == pytest.approx(want, abs=1e-9)
    # float32 leaves ~1e-7 of spurious variance (E[x^2] - E[x]^2), which C2 = 9e-4 turns into ~1e-4.
    assert float(ssim(torch.full((12, 12, 3), a), torch.full((12, 12, 3), b))) == pytest.approx(want, abs=1e-3)


@pytest.mark.parametrize("shape,window", [((1, 37, 53, 3), 11), ((2, 20, 16, 1), 11), ((1, 9, 40, 3), 7)])
def test_ssim_matches_kornias_and_so_do_its_gradients(shape, window):
    """ssim filters the five local moments in one stacked pass; kornia.metrics.ssim, five passes, is the reference."""
    from kornia.metrics import ssim as kornia_ssim

    g = torch.Generator().manual_seed(3)
    x = torch.rand(shape, generator=g, dtype=torch.float64).requires_grad_(True)
    y = (x.detach() + 0.2 * torch.randn(shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    ours = ssim(x, y, window_size=window)
    (g_ours,) = torch.autograd.grad(ours, x)
    ref = kornia_ssim(x.permute(0, 3, 1, 2), y.permute(0, 3, 1, 2), window, max_val=1.0).mean()
    (g_ref,) = torch.autograd.grad(ref, x)
    assert 0.2 < float(ref) < 0.95  # neither identical nor unrelated images: the comparison means something
    assert float(ours) == pytest.approx(float(ref), abs=1e-12)
    torch.testing.assert_close(g_ours, g_ref, rtol=1e-9, atol=1e-12)
    assert float(ssim(x.float(), y.float(), window_size=window)) == pytest.approx(float(ref), abs=1e-5)


def test_ssim_on_images_smaller_than_the_window():
    x = torch.rand(2, 3, 5, 3, generator=torch.Generator().manual_seed(1))
    assert float(ssim(x, x)) == pytest.approx(1.0, abs=1e-6)
    assert float(ssim(x, 1 - x)) < 0.9


def test_an_ssim_under_inference_mode_leaves_later_ones_differentiable():
    """The window is built once per size and device: made under inference_mode it could not be saved for the
    backward of any SSIM after it (the training D-SSIM included)."""
    metrics._gaussian_window.cache_clear()
    a, b = torch.rand(24, 20, 3), torch.rand(24, 20, 3)
    with torch.inference_mode():
        ssim(a, b)
    x = a.clone().requires_grad_(True)
    ssim(x, b).backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()


def test_shape_errors():
    with pytest.raises(ValueError, match="shapes differ"):
        psnr(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))
    with pytest.raises(ValueError, match="pred"):
        ssim(torch.zeros(3, 4, 4), torch.zeros(3, 4, 4))  # CHW is not accepted


def test_lpips_unavailable_here_is_reported(monkeypatch):
    monkeypatch.setattr(metrics.importlib.util, "find_spec", lambda name: None)
    m = LPIPSMetric()
    assert not m.available and "lpips" in m.reason
    assert m(torch.zeros(4, 4, 3), torch.zeros(4, 4, 3)) is None
    out = image_metrics(torch.zeros(8, 8, 3), torch.full((8, 8, 3), 0.1), m)
    assert out["lpips"] is None and "lpips" in out["lpips_unavailable"]
    assert out["psnr"] == pytest.approx(20.0, abs=1e-4)
    assert "net" in lpips_unavailable_reason("resnet")


FAKE_LPIPS = '''
import torch
class LPIPS(torch.nn.Module):
    def __init__(self, net="alex", verbose=True):
        super().__init__()
        self.w = torch.nn.Parameter(torch.ones(()))
    def forward(self, a, b, normalize=False):
        if normalize:
            a, b = a * 2 - 1, b * 2 - 1
        return (a - b).abs().mean((1, 2, 3)) * self.w
'''


def test_lpips_needs_local_weights(tmp_path, monkeypatch):
    pkg = tmp_path / "site" / "lpips"
    (pkg / "weights" / "v0.1").mkdir(parents=True)
    (pkg / "__init__.py").write_text(FAKE_LPIPS)
    hub = tmp_path / "hub"
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(hub))
    monkeypatch.delitem(sys.modules, "lpips", raising=False)
    try:
        assert "linear weights" in LPIPSMetric().reason
        (pkg / "weights" / "v0.1" / "alex.pth").write_bytes(b"x")
        assert "backbone" in LPIPSMetric().reason  # and nothing was downloaded
        (hub / "checkpoints").mkdir(parents=True)
        (hub / "checkpoints" / "alexnet-owt-7be5be79.pth").write_bytes(b"x")
        m = LPIPSMetric()
        assert m.available and m.reason is None
        # Inputs are mapped from [0,1] to [-1,1]: a 0.1 difference becomes 0.2.
        assert float(m(torch.zeros(4, 4, 3), torch.full((4, 4, 3), 0.1))) == pytest.approx(0.2)
        assert image_metrics(torch.zeros(4, 4, 3), torch.full((4, 4, 3), 0.1), m)["lpips"] == pytest.approx(0.2)
    finally:
        sys.modules.pop("lpips", None)
