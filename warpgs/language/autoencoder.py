"""The per-scene autoencoder 512 -> d -> 512 (LangSplat's, d = 8 here): trained once on the scene's segment
features with an L1 + cosine loss; its encoder turns feature maps into d-dim training targets, its decoder turns
rendered latents back into CLIP space at query time.

Both ends are L2-normalised: latents are unit vectors in R^d (rendered latents are their alpha blends) and
decoded features are unit vectors in R^512 like CLIP's.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

FORMAT = "warpgs-language-autoencoder"


@dataclass
class AutoencoderConfig:
    in_dim: int = 512
    latent_dim: int = 8
    encoder_hidden: List[int] = field(default_factory=lambda: [256, 64])
    decoder_hidden: List[int] = field(default_factory=lambda: [64, 256])


def _mlp(sizes: Sequence[int]) -> nn.Sequential:
    layers: list = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


class FeatureAutoencoder(nn.Module):
    def __init__(self, config: Optional[AutoencoderConfig] = None, **kwargs):
        super().__init__()
        self.config = config or AutoencoderConfig(**kwargs)
        c = self.config
        if c.latent_dim < 1 or c.in_dim < 2:
            raise ValueError(f"autoencoder: need in_dim >= 2 and latent_dim >= 1, got {c.in_dim}, {c.latent_dim}")
        self.encoder = _mlp([c.in_dim, *c.encoder_hidden, c.latent_dim])
        self.decoder = _mlp([c.latent_dim, *c.decoder_hidden, c.in_dim])

    @property
    def latent_dim(self) -> int:
        return self.config.latent_dim

    @property
    def in_dim(self) -> int:
        return self.config.in_dim

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """[..., in_dim] -> [..., latent_dim] unit vectors."""
        return F.normalize(self.encoder(x), dim=-1, eps=1e-8)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """[..., latent_dim] -> [..., in_dim] unit vectors."""
        return F.normalize(self.decoder(z), dim=-1, eps=1e-8)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decode(self.encode(x))

    # ----- persistence -----
    def save(self, path) -> Path:
        from warpgs.utils.atomic_file import atomic_write_bytes
        import io

        buf = io.BytesIO()
        torch.save({"format": FORMAT, "config": asdict(self.config),
                    "state": {k: v.detach().cpu() for k, v in self.state_dict().items()}}, buf)
        atomic_write_bytes(path, buf.getvalue())
        return Path(path)

    @classmethod
    def load(cls, path, device=None) -> "FeatureAutoencoder":
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: autoencoder file not found")
        try:
            blob = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:
            raise ValueError(f"{path}: not a readable autoencoder ({type(e).__name__}: {e})") from None
        if not isinstance(blob, dict) or blob.get("format") != FORMAT:
            raise ValueError(f"{path}: not a warpgs language autoencoder")
        model = cls(AutoencoderConfig(**blob["config"]))
        model.load_state_dict(blob["state"])
        return model.to(device).eval()


def reconstruction_loss(pred: torch.Tensor, target: torch.Tensor, cos_weight: float = 1.0) -> torch.Tensor:
    """Mean L1 + cos_weight * mean (1 - cosine)."""
    l1 = (pred - target).abs().mean()
    cos = 1.0 - F.cosine_similarity(pred, target, dim=-1, eps=1e-8).mean()
    return l1 + cos_weight * cos


@dataclass
class AutoencoderReport:
    steps: int
    seconds: float
    final_loss: float
    train_cosine: float  # mean cosine between features and their reconstructions (training set)


def train_autoencoder(features, *, latent_dim: int = 8, steps: int = 400, lr: float = 3e-3,
                      batch_size: int = 256, cos_weight: float = 1.0, seed: int = 0, device=None,
                      config: Optional[AutoencoderConfig] = None, threads: Optional[int] = 1) -> tuple:
    """Fit an autoencoder to features [M, in_dim] (numpy or torch); returns (model in eval mode, report).

    Deterministic for a given seed (own generator; the global RNG is left as it was). threads: torch CPU
    threads while training (1 is fastest for these small layers; the previous setting is restored).
    """
    previous = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    try:
        return _train(features, latent_dim, steps, lr, batch_size, cos_weight, seed, device, config)
    finally:
        torch.set_num_threads(previous)


def _train(features, latent_dim, steps, lr, batch_size, cos_weight, seed, device, config):
    x = torch.as_tensor(np.asarray(features) if not torch.is_tensor(features) else features).float()
    if x.dim() != 2 or x.shape[0] < 1:
        raise ValueError(f"features: expected [M, C] with M >= 1, got {list(x.shape)}")
    if not torch.isfinite(x).all():
        raise ValueError("features: contain NaN or Inf")
    x = F.normalize(x, dim=-1, eps=1e-8).to(device)
    cfg = config or AutoencoderConfig(in_dim=x.shape[1], latent_dim=latent_dim)
    if cfg.in_dim != x.shape[1]:
        raise ValueError(f"features: {x.shape[1]} channels but the autoencoder expects {cfg.in_dim}")
    gen = torch.Generator().manual_seed(int(seed))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        model = FeatureAutoencoder(cfg).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    t0 = time.perf_counter()
    loss = torch.zeros(())
    model.train()
    for _ in range(int(steps)):
        idx = torch.randint(0, x.shape[0], (min(batch_size, x.shape[0]),), generator=gen).to(x.device)
        batch = x[idx]
        loss = reconstruction_loss(model(batch), batch, cos_weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        cos = float(reconstruction_cosine(model, x))
    return model, AutoencoderReport(int(steps), time.perf_counter() - t0, float(loss.detach()), cos)


@torch.no_grad()
def reconstruction_cosine(model: FeatureAutoencoder, features) -> float:
    """Mean cosine similarity between features [M, C] and model(features)."""
    x = torch.as_tensor(np.asarray(features) if not torch.is_tensor(features) else features).float()
    x = x.to(next(model.parameters()).device)
    if x.shape[0] == 0:
        return math.nan
    return float(F.cosine_similarity(model(x), x, dim=-1).mean())
