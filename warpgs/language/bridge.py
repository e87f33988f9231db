"""The PPGS bridge module: a per-primitive MLP from the centre position to a colour and a language latent.

    enc = PE(normalise(p))                 NeRF positional encoding, [p, sin(2^k pi p), cos(2^k pi p)]_{k<L}
    h   = ReLU(W_4 ... ReLU(W_1 enc))      shared trunk: `depth` layers of `width` channels
    h   = [h, enc]                         skip: the encoding concatenated back in (96 + 63 = 159 channels)
    c   = sigmoid(W_c h)                   colour head, 3 channels in [0, 1]
    f   = W_f h                            language head, d channels

Positions are normalised with a fixed centre and scale (buffers, set once from the initial primitives with
`fit_normalisation`), so the encoding's frequencies mean the same thing in every scene.
"""
from __future__ import annotations

import math
from typing import Optional, Tuple

import torch
from torch import nn


def positional_encoding(x: torch.Tensor, n_freqs: int, include_input: bool = True) -> torch.Tensor:
    """[..., D] -> [..., D (if include_input) + 2 D n_freqs]: sin/cos of 2^k pi x, grouped by frequency."""
    if n_freqs < 0:
        raise ValueError(f"n_freqs: expected >= 0, got {n_freqs}")
    parts = [x] if include_input else []
    if n_freqs:
        freqs = (2.0 ** torch.arange(n_freqs, dtype=x.dtype, device=x.device)) * math.pi
        angles = x[..., None, :] * freqs[:, None]  # [..., L, D]
        parts += [torch.sin(angles).flatten(-2), torch.cos(angles).flatten(-2)]
    if not parts:
        raise ValueError("positional_encoding: n_freqs=0 and include_input=False leave nothing")
    return torch.cat(parts, -1)


def encoding_dim(n_freqs: int, include_input: bool = True, in_dim: int = 3) -> int:
    return in_dim * (int(include_input) + 2 * n_freqs)


class BridgeMLP(nn.Module):
    """See the module docstring. `color=False` / `language=False` drop a head (the paper's single-branch
    ablations); the forward pass then returns None for it."""

    def __init__(self, lang_dim: int = 8, *, n_freqs: int = 10, width: int = 96, depth: int = 4,
                 skip: bool = True, include_input: bool = True, color: bool = True, language: bool = True,
                 color_dim: int = 3):
        super().__init__()
        if depth < 1 or width < 1:
            raise ValueError(f"bridge: need depth >= 1 and width >= 1, got {depth}, {width}")
        if not (color or language):
            raise ValueError("bridge: at least one of the colour and language heads is needed")
        self.n_freqs, self.include_input, self.skip = int(n_freqs), bool(include_input), bool(skip)
        enc = encoding_dim(self.n_freqs, self.include_input)
        layers = []
        for i in range(depth):
            layers += [nn.Linear(enc if i == 0 else width, width), nn.ReLU(inplace=True)]
        self.trunk = nn.Sequential(*layers)
        head_in = width + (enc if self.skip else 0)
        self.color_head = nn.Linear(head_in, color_dim) if color else None
        self.lang_head = nn.Linear(head_in, lang_dim) if language else None
        self.register_buffer("centre", torch.zeros(3))
        self.register_buffer("scale", torch.ones(()))

    @property
    def head_in_dim(self) -> int:
        return (self.color_head or self.lang_head).in_features

    @torch.no_grad()
    def fit_normalisation(self, points: torch.Tensor, margin: float = 1.1) -> None:
        """Centre on the points' bounding-box middle and scale so they fall in [-1/margin, 1/margin]^3."""
        pts = points.detach().float()
        if pts.numel() == 0:
            return
        lo, hi = pts.min(0).values, pts.max(0).values
        self.centre.copy_((lo + hi) / 2)
        half = float(((hi - lo) / 2).max())
        self.scale.fill_(max(half * margin, 1e-6))

    def encode(self, means: torch.Tensor) -> torch.Tensor:
        return positional_encoding((means - self.centre) / self.scale, self.n_freqs, self.include_input)

    def features(self, means: torch.Tensor) -> torch.Tensor:
        """The shared representation [N, head_in_dim] the heads read."""
        enc = self.encode(means)
        h = self.trunk(enc)
        return torch.cat([h, enc], -1) if self.skip else h

    def forward(self, means: torch.Tensor) -> Tuple[Optional[torch.Tensor], Optional[torch.Tensor]]:
        """means [N, 3] -> (colour [N, 3] in [0, 1] or None, latent [N, d] or None)."""
        h = self.features(means)
        color = torch.sigmoid(self.color_head(h)) if self.color_head is not None else None
        lang = self.lang_head(h) if self.lang_head is not None else None
        return color, lang
