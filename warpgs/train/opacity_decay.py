"""Decoupled opacity decay (train.opacity_decay): every step, after the optimizers, each primitive's opacity is
multiplied by (1 - d).

Why not the `opacity` loss (mean α, the Gestalt paper's eq. 9)? Its gradient per primitive is tiny (λ / N), but Adam
divides every gradient by its own running scale, so a primitive the photometric loss barely touches (fine detail
seen in few views) gets a full learning-rate step down at every step, whatever λ is. Decay applied outside the
optimizer (as AdamW decouples weight decay) moves every primitive by the same small fraction; the photometric
gradient, through Adam, wins wherever it has any say, and only primitives nothing needs fade.

In logits, with α = sigmoid(x) and a = α (1 - d):  x' = logit(a) = x + log(1 - d) + log(1 - α) - log(1 - a), where
1 - a = (1 - α) + d α; each log is taken from log-sigmoids (never of a rounded 1 - α), so any finite logit gives a
finite one.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def decayed_logits(logits: torch.Tensor, decay: float) -> torch.Tensor:
    """The logits of sigmoid(logits) * (1 - decay), for 0 <= decay < 1."""
    if not 0.0 <= decay < 1.0:
        raise ValueError(f"train.opacity_decay: expected a fraction in [0, 1), got {decay}")
    if decay == 0.0:
        return logits
    log_off = F.logsigmoid(-logits)  # log(1 - α)
    log_kept_off = torch.logaddexp(log_off, math.log(decay) + F.logsigmoid(logits))  # log(1 - α + d α)
    return logits + math.log1p(-decay) + log_off - log_kept_off


def decay_opacities(model, decay: float) -> None:
    """Apply one step of decay to the model's opacity logits in place (no autograd, optimizer state untouched)."""
    if decay <= 0.0:
        return
    logits = model.logit_opacities
    with torch.no_grad():
        logits.copy_(decayed_logits(logits, decay))
