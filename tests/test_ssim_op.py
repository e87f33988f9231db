"""The Warp SSIM op (render/ssim_op.py, kernels/ssim.py) against the torch SSIM in float64: value and gradient,
the filter's adjoint against the transpose of its matrix, and how the trainer installs it for the D-SSIM term."""
import numpy as np
import pytest
import torch
import warp as wp

from warpgs.kernels import ssim as kernels
from warpgs.losses import photometric
from warpgs.metrics.image import _gaussian_window, ssim
from warpgs.render.ssim_op import fused_ssim


def reference(pred, target):
    """SSIM and its gradient in float64 through torch's autograd."""
    p64 = pred.detach().double().requires_grad_(True)
    value = ssim(p64, target.double())
    value.backward()
    return value.item(), p64.grad


@pytest.mark.parametrize("shape", [(20, 17, 3), (2, 13, 31, 3), (5, 4, 1), (40, 33, 1), (3, 9, 8, 3)])
def test_value_and_gradient_match_float64(shape):
    g = torch.Generator().manual_seed(sum(shape))
    pred = torch.rand(shape, generator=g).requires_grad_(True)
    target = (0.7 * pred.detach() + 0.3 * torch.rand(shape, generator=g)).clamp(0, 1)  # correlated: SSIM ~ 0.5+
    value = fused_ssim(pred, target)
    value.backward()
    want, want_grad = reference(pred, target)
    assert abs(value.item() - want) < 2e-6
    scale = want_grad.abs().max().item()
    assert (pred.grad.double() - want_grad).abs().max().item() < 1e-4 * scale
    assert torch.isfinite(pred.grad).all()


def test_a_second_derivative_is_refused():
    """The op's backward is Warp kernels: create_graph=True through it raises instead of dropping its part of a
    gradient penalty (SSIM ends in a mean, so torch's once_differentiable would let it through)."""
    pred = torch.rand(12, 10, 3, generator=torch.Generator().manual_seed(2)).requires_grad_(True)
    with pytest.raises(RuntimeError, match="Warp SSIM.*not differentiable"):
        torch.autograd.grad(fused_ssim(pred, torch.rand(12, 10, 3)), [pred], create_graph=True)


def test_identical_images_give_one_and_a_zero_gradient():
    img = torch.rand(16, 12, 3, generator=torch.Generator().manual_seed(1)).requires_grad_(True)
    value = fused_ssim(img, img.detach().clone())
    value.backward()
    assert abs(value.item() - 1.0) < 1e-5
    assert img.grad.abs().max().item() < 1e-4  # SSIM is at its maximum


def blur_matrix(n: int, weights: np.ndarray) -> np.ndarray:
    half = len(weights) // 2
    m = np.zeros((n, n))
    for o in range(n):
        for k, w in enumerate(weights):
            j = o + k - half
            j = -j if j < 0 else (2 * (n - 1) - j if j > n - 1 else j)
            m[o, j] += w
    return m


@pytest.mark.parametrize("n,size", [(6, 11), (11, 11), (30, 11), (4, 7), (2, 3)])
def test_filter_and_adjoint_are_the_reflected_matrix_and_its_transpose(n, size):
    """Along W (rows of n, 3 channels): the moments' filter against the matrix, its adjoint (through the input
    gradient with y = 0 and only d mean(x) set, which is then the adjoint itself) against the transpose."""
    weights = _gaussian_window(size, torch.device("cpu"), torch.float32).reshape(-1).numpy()
    rows, channels = 2, 3
    rng = np.random.default_rng(n)
    x = rng.random((rows, n, channels)).astype(np.float32)
    m = blur_matrix(n, weights.astype(np.float64))
    w = wp.array(weights, dtype=float, device="cpu")
    flat = lambda a: wp.array(a.reshape(-1), dtype=float, device="cpu")
    out = wp.zeros(x.size, dtype=kernels.Moments, device="cpu")
    wp.launch(kernels.blur_moments_along_w, dim=x.size, inputs=[flat(x), flat(x), w, n, channels], outputs=[out],
              device="cpu")
    got = out.numpy().reshape(rows, n, channels, 5)
    assert np.abs(got[..., 0] - np.einsum("oi,ric->roc", m, x)).max() < 1e-5
    assert np.abs(got[..., 2] - np.einsum("oi,ric->roc", m, x.astype(np.float64) ** 2)).max() < 1e-5
    upstream = np.zeros((x.size, 3), dtype=np.float32)
    upstream[:, 0] = x.reshape(-1)
    grad = wp.zeros(x.size, dtype=float, device="cpu")
    wp.launch(kernels.input_grad_along_w, dim=x.size,
              inputs=[wp.array(upstream, dtype=kernels.MomentGrads, device="cpu"), w, n, channels, flat(x),
                      flat(np.zeros_like(x))], outputs=[grad], device="cpu")
    want = np.einsum("oi,roc->ric", m, x.astype(np.float64))  # the transpose applied
    assert np.abs(grad.numpy().reshape(rows, n, channels) - want).max() < 1e-5


def test_bad_arguments_are_named():
    pred = torch.rand(8, 8, 3, requires_grad=True)
    with pytest.raises(ValueError, match="target"):
        fused_ssim(pred, torch.rand(8, 8, 3, requires_grad=True))
    with pytest.raises(ValueError, match="float32"):
        fused_ssim(pred.double(), torch.rand(8, 8, 3).double())
    with pytest.raises(ValueError, match="shapes differ"):
        fused_ssim(pred, torch.rand(8, 9, 3))


def test_trainer_setting_installs_it_for_the_dssim_term():
    from warpgs.train.setup import install_training_ssim

    try:
        install_training_ssim("auto", torch.device("cpu"))  # on the CPU torch's filters are the faster
        assert photometric._installed_ssim is None
        install_training_ssim(True, torch.device("cpu"))
        assert photometric._installed_ssim.fn is fused_ssim
        pred = torch.rand(12, 10, 3, requires_grad=True)
        target = torch.rand(12, 10, 3)
        assert abs(photometric.training_ssim(pred, target).item() - ssim(pred, target).item()) < 1e-5
        install_training_ssim(False, torch.device("cpu"))
        assert photometric._installed_ssim is None
        assert photometric.training_ssim(pred, target).item() == ssim(pred, target).item()
    finally:
        photometric.use_training_ssim(None)


def test_a_short_training_run_with_it(tmp_path):
    from warpgs.config.loader import load_config
    from warpgs.train.trainer import Trainer

    cfg = load_config(None, ["steps=3", "train.fused_ssim=true", "train.device=cpu", "eval.every=0",
                             "data.width=32", "data.height=24", f"output.dir={tmp_path}", "train.progress=false"])
    try:
        trainer = Trainer(cfg, quiet=True)
        assert photometric._installed_ssim.fn is fused_ssim
        for _ in range(3):
            trainer.train_step()
        assert trainer.num_primitives > 0
    finally:
        photometric.use_training_ssim(None)


def test_on_torch_stream_scopes_the_warp_device_on_the_cpu():
    from warpgs.render.torch_streams import on_torch_stream, warp_device

    assert warp_device(torch.device("cpu")) == wp.get_device("cpu")
    with on_torch_stream(torch.device("cpu")):
        assert wp.get_device() == wp.get_device("cpu")


@pytest.mark.parametrize("given, expected", [("auto", "auto"), ("AUTO", "auto"), (True, True), ("false", False),
                                             ("on", True), (0, False)])
def test_the_setting_takes_true_false_or_auto(given, expected):
    from warpgs.config.loader import load_config

    assert load_config(None, [f"train.fused_ssim={given}"]).train.fused_ssim == expected


def test_a_bad_setting_is_named():
    from warpgs.config.loader import load_config
    from warpgs.config.schema import ConfigError

    with pytest.raises(ConfigError, match="train.fused_ssim.*true, false or 'auto'"):
        load_config(None, ["train.fused_ssim=sometimes"])
