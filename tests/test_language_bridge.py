"""Bridge MLP: encoding size, shapes, value ranges, gradients to the centres and every weight."""
import math

import pytest
import torch

from warpgs.language.bridge import BridgeMLP, encoding_dim, positional_encoding


def test_positional_encoding_layout():
    x = torch.tensor([[0.25, -0.5, 1.0]])
    enc = positional_encoding(x, 2)
    assert enc.shape == (1, 3 + 2 * 3 * 2)
    assert torch.equal(enc[0, :3], x[0])
    # sin block then cos block, frequency-major: sin(pi x), sin(2 pi x)
    assert torch.allclose(enc[0, 3:6], torch.sin(math.pi * x[0]))
    assert torch.allclose(enc[0, 6:9], torch.sin(2 * math.pi * x[0]))
    assert torch.allclose(enc[0, 9:12], torch.cos(math.pi * x[0]))
    assert encoding_dim(10) == 63


def test_bridge_shapes_and_paper_sizes():
    torch.manual_seed(0)
    bridge = BridgeMLP(8)
    assert bridge.head_in_dim == 96 + 63 == 159  # the paper's 159-d skip concatenation
    linears = [m for m in bridge.trunk if isinstance(m, torch.nn.Linear)]
    assert [l.out_features for l in linears] == [96, 96, 96, 96]
    means = torch.randn(50, 3) * 3
    bridge.fit_normalisation(means)
    c, f = bridge(means)
    assert c.shape == (50, 3) and f.shape == (50, 8)
    assert bool(((c > 0) & (c < 1)).all())
    assert bool(torch.isfinite(f).all())
    scaled = (means - bridge.centre) / bridge.scale
    assert float(scaled.abs().max()) <= 1.0


def test_bridge_gradients_reach_centres_and_weights():
    torch.manual_seed(1)
    bridge = BridgeMLP(4, n_freqs=4, width=16, depth=2)
    means = torch.randn(20, 3, requires_grad=True)
    c, f = bridge(means)
    (c.sum() + f.pow(2).sum()).backward()
    assert means.grad is not None and float(means.grad.abs().sum()) > 0
    for name, p in bridge.named_parameters():
        assert p.grad is not None and float(p.grad.abs().sum()) > 0, name


def test_bridge_options():
    b = BridgeMLP(8, skip=False, width=32, depth=3, color=False)
    c, f = b(torch.zeros(5, 3))
    assert c is None and f.shape == (5, 8) and b.head_in_dim == 32
    with pytest.raises(ValueError):
        BridgeMLP(8, color=False, language=False)
