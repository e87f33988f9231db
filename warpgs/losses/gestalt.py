"""The Gestalt / Prägnanz terms of the sparse-view method: penalties on the primitives themselves.

Registered losses (they read the model, not the render, so they ask for no render outputs):

    opacity   mean_i α_i                                   λ4 = 0.05   (paper eq. 9)
    scale     mean_i ‖s_i‖₂  (activated scales)            λ5 = 0.008  (paper eq. 10)
    count     log Σ_i sigmoid((α_i - τ) / T)               λ6 = 0.001  (paper eq. 11 writes log N)

`count`: the paper's log N_Gauss is a constant with respect to every parameter, so as written it does nothing
to the optimisation. We replace N by a soft count of the primitives that are "on": a primitive with opacity well
above τ counts ~1, one well below counts ~0, and the term's gradient pushes primitives near the threshold
further down, where the densification strategy's opacity pruning removes them; the strategy's hard budget
(`strategy.max_primitives`) caps growth from the other side. τ and T are in `SETTINGS` (defaults τ = 0.005, the
strategy's default prune_opacity, and T = 0.05). The value is log of a count, so it is ~log N when most
primitives are opaque, as in the paper.

All three are means over the current primitives (an empty model gives 0, still connected to the graph). With
model-parallel training the model is one rank's share: the sums and counts then run over every rank's rows
(`model.reduce_rows`, a differentiable all-reduce), so each rank's term and its gradients are the whole model's.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from warpgs.losses.registry import register_loss


@dataclass
class GestaltSettings:
    count_tau: float = 0.005  # opacity at which a primitive counts one half
    count_temperature: float = 0.05  # width of the soft step (in opacity units)


SETTINGS = GestaltSettings()


def configure(**kwargs) -> GestaltSettings:
    """Change the module's settings (see GestaltSettings); returns them."""
    names = {f.name for f in fields(GestaltSettings)}
    for key, value in kwargs.items():
        if key not in names:
            raise ValueError(f"gestalt.configure: unknown setting {key!r}; choose from {sorted(names)}")
        value = float(value)
        if not (value == value and abs(value) < float("inf")):
            raise ValueError(f"gestalt.configure: {key} must be finite, got {value}")
        if key == "count_temperature" and value <= 0:
            raise ValueError(f"gestalt.configure: count_temperature must be > 0, got {value}")
        setattr(SETTINGS, key, value)
    return SETTINGS


# ----- per-primitive quantities -------------------------------------------------------------------------------
def scale_norms(scales: torch.Tensor) -> torch.Tensor:
    """‖s_i‖₂ of [N, k] scales, [N]; the norm's gradient is guarded at s = 0."""
    sq = (scales * scales).sum(-1)
    return torch.where(sq > 0, sq.clamp_min(1e-30).sqrt(), torch.zeros_like(sq))


def soft_on(opacities: torch.Tensor, tau: float, temperature: float) -> torch.Tensor:
    """sigmoid((α_i - τ) / T), [N]: how much each primitive counts."""
    return torch.sigmoid((opacities.reshape(-1) - tau) / temperature)


# ----- registered terms ----------------------------------------------------------------------------------------
def _opacities(model) -> torch.Tensor:
    return model.opacities


def _sum_over_rows(model, per_row: torch.Tensor):
    """(Σ per_row, number of rows) over the whole model: a model-parallel shard's `reduce_rows` adds the other
    ranks' (in one all-reduce); a whole model has none."""
    # new_full fills on the device; new_tensor would copy from the host (and torch syncs after such a copy).
    local = torch.stack([per_row.sum(), per_row.new_full((), float(per_row.numel()))])
    reduce = getattr(model, "reduce_rows", None)
    total = local if reduce is None else reduce(local)
    return total[0], total[1]


def _mean_over_rows(model, per_row: torch.Tensor) -> torch.Tensor:
    total, n = _sum_over_rows(model, per_row)
    return total / n.clamp_min(1.0)


@register_loss("opacity", outputs=(), weight=0.05)
def opacity(render_out, batch, model, step) -> torch.Tensor:
    """L_o = mean_i α_i."""
    return _mean_over_rows(model, _opacities(model).reshape(-1))


@register_loss("scale", outputs=(), weight=0.008)
def scale(render_out, batch, model, step) -> torch.Tensor:
    """L_s = mean_i ‖s_i‖₂."""
    return _mean_over_rows(model, scale_norms(model.scales))


@register_loss("count", outputs=(), weight=0.001)
def count(render_out, batch, model, step) -> torch.Tensor:
    """L_count = log(Σ_i sigmoid((α_i - τ) / T) + 1e-6) (a differentiable log N, see the module doc): log N when
    every primitive is well above τ; finite (log 1e-6) for an empty model."""
    on, _ = _sum_over_rows(model, soft_on(_opacities(model), SETTINGS.count_tau, SETTINGS.count_temperature))
    return torch.log(on + 1e-6)
