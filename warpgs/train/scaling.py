"""Adam settings for a batch of B views per step (train.batch_size, summed over the ranks of a distributed run).

`train.batch_scaling: sqrt` (the default) follows gsplat's simple_trainer, which cites the square-root scaling
rule for adaptive optimizers (Malladi et al. 2022, "On the SDEs and Scaling Rules for Adaptive Gradient
Algorithms"): learning rate x sqrt(B), Adam's epsilon / sqrt(B), and 1 - beta x B for both betas. The loss is the
mean over the B views, so the gradient's noise falls as 1/sqrt(B) and the larger step keeps the same progress per
view seen; the betas rule keeps the moments' memory the same number of *views* long. gsplat notes the betas rule
breaks down for B >= 10 (beta1 reaches 0); here it is clamped at 0 instead of failing. `none` leaves Adam as
configured (use it to compare, or when the learning rates were tuned for the batch already).

The schedule stays in optimizer steps: `train.steps`, the position-lr decay, `refine_*` and `reset_every` count
steps of B views. A run of S steps at B=1 sees as many views as S/B steps at batch B; gsplat's users divide the
steps by B themselves (its `--steps_scaler 0.25` for 4 GPUs), and so do ours (docs/distributed.md).
B = 1 leaves every setting exactly as configured (no arithmetic at all), so single-view runs are unchanged.
"""
from __future__ import annotations

import math
from typing import Dict, Iterable, Tuple

import torch

RULES = ("sqrt", "none")


def lr_scale(batch_size: int, rule: str) -> float:
    """The learning-rate multiplier for a batch of `batch_size` views."""
    if rule not in RULES:
        raise ValueError(f"train.batch_scaling: expected one of {list(RULES)}, got {rule!r}")
    return math.sqrt(batch_size) if rule == "sqrt" and batch_size > 1 else 1.0


def adam_settings(batch_size: int, rule: str, eps: float, betas: Tuple[float, float]) -> tuple:
    """(eps, betas) for the batch: eps / sqrt(B) and 1 - B (1 - beta) clamped to [0, 1) under "sqrt"."""
    scale = lr_scale(batch_size, rule)
    if scale == 1.0:
        return eps, tuple(betas)
    return eps / scale, tuple(max(0.0, 1.0 - batch_size * (1.0 - b)) for b in betas)


def apply_batch_scaling(optimizers: Iterable[torch.optim.Optimizer], base_lrs: Dict[str, float], *,
                        batch_size: int, rule: str) -> None:
    """Set every named group's lr to base_lrs[name] x the batch's multiplier, and its eps and betas from the
    optimizer's own constructor values (`opt.defaults`) as adam_settings says. Absolute values, so applying it
    twice (or after loading a checkpoint of another batch size) is safe. Groups not in base_lrs keep their lr."""
    scale = lr_scale(batch_size, rule)
    for opt in optimizers:
        eps, betas = adam_settings(batch_size, rule, opt.defaults["eps"], opt.defaults["betas"])
        for group in opt.param_groups:
            name = group.get("name")
            if name in base_lrs:
                group["lr"] = base_lrs[name] * scale if scale != 1.0 else base_lrs[name]
            group["eps"], group["betas"] = eps, betas
