"""Adam with the 3DGS learning rates, the exponential position schedule, and optimizer-state surgery.

Surgery: densification changes the number of primitives, so every per-primitive Parameter is replaced by a
new one and its Adam moments (exp_avg, exp_avg_sq, ...) are re-indexed to match: kept rows carry their
moments, new rows start at zero (as 3DGS and gsplat do). Any optimizer/param group holding one of the model's
parameters is updated; other groups (an MLP, uncertainty weights) are left alone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Dict, Iterable, Mapping, Optional, Union

import torch
from torch import nn

from warpgs.model.gaussians import GaussianModel

Optimizers = Union[torch.optim.Optimizer, Iterable[torch.optim.Optimizer]]
MOMENTS = ("exp_avg", "exp_avg_sq")  # Adam's per-row state; "step" is a scalar


@dataclass
class OptimConfig:
    means_lr: float = 1.6e-4  # x scene extent, at step 0
    means_lr_final: float = 1.6e-6  # x scene extent, reached at max_steps (log-linear in between)
    # The decay's length in steps (0: the run's length). A run cut short of a longer schedule sets it to that
    # schedule's length, so it follows the longer run's curve (3DGS's position_lr_max_steps; sparse_llff_baseline).
    means_lr_steps: int = 0
    means_lr_delay_steps: int = 0  # optional warm-up as 3DGS's delay (0: none)
    means_lr_delay_mult: float = 0.01
    scales_lr: float = 5e-3
    quats_lr: float = 1e-3
    opacities_lr: float = 2.5e-2  # later 3DGS releases; the paper's 0.05 also works
    sh0_lr: float = 2.5e-3
    shN_lr: float = 2.5e-3 / 20
    extra_lr: float = 1e-3  # for extras not named in extras_lr
    extras_lr: Dict[str, float] = field(default_factory=dict)
    eps: float = 1e-15  # 3DGS's Adam epsilon: gradients of far/small primitives are tiny
    beta1: float = 0.9
    beta2: float = 0.999
    # "fused": Adam's fused kernel, one launch per parameter instead of about eight; "foreach": torch's default;
    # "auto": fused on CUDA, where a training step is bound by host time. The two agree to rounding.
    adam_kernel: str = "auto"

    def __post_init__(self):
        if self.adam_kernel not in ("auto", "fused", "foreach"):
            raise ValueError(f"adam_kernel: expected 'auto', 'fused' or 'foreach', got {self.adam_kernel!r}")
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{f.name}: expected a finite non-negative number, got {v}")
        for name, v in self.extras_lr.items():
            if not (math.isfinite(float(v)) and v >= 0):
                raise ValueError(f"extras_lr.{name}: expected a finite non-negative number, got {v}")
        if isinstance(self.means_lr_steps, bool) or not isinstance(self.means_lr_steps, int) \
                or self.means_lr_steps < 0:
            raise ValueError(f"means_lr_steps: expected a non-negative integer (0: the run's length), "
                             f"got {self.means_lr_steps!r}")
        if self.means_lr > 0 and self.means_lr_final <= 0:
            raise ValueError("means_lr_final: must be > 0 for the exponential decay (set means_lr=0 to freeze)")

    def lr_for(self, name: str, scene_extent: float) -> float:
        fixed = {"means": self.means_lr * scene_extent, "log_scales": self.scales_lr, "quats": self.quats_lr,
                 "logit_opacities": self.opacities_lr, "sh0": self.sh0_lr, "shN": self.shN_lr}
        if name in fixed:
            return fixed[name]
        return float(self.extras_lr.get(name, self.extra_lr))


def _check_extent(scene_extent: float) -> float:
    if not (math.isfinite(float(scene_extent)) and scene_extent > 0):
        raise ValueError(f"scene_extent: expected a finite positive number, got {scene_extent}")
    return float(scene_extent)


def fused_adam(adam_kernel: str, *, on_cuda: bool) -> bool:
    """Whether optim.adam_kernel picks Adam's fused kernel for parameters on CUDA (on_cuda) or not."""
    return adam_kernel == "fused" or (adam_kernel == "auto" and on_cuda)


def build_optimizer(model: GaussianModel, config: Optional[OptimConfig] = None,
                    scene_extent: float = 1.0) -> torch.optim.Adam:
    """One Adam, one named group per parameter (group["name"] is the key in model.params)."""
    config = config or OptimConfig()
    extent = _check_extent(scene_extent)
    unknown = [n for n in config.extras_lr if n not in model.params]
    if unknown:
        raise ValueError(f"extras_lr: no such model parameters {unknown}; have {list(model.params)}")
    groups = [{"params": [p], "lr": config.lr_for(name, extent), "name": name} for name, p in model.params.items()]
    fused = fused_adam(config.adam_kernel, on_cuda=all(p.is_cuda for p in model.params.values()))
    return torch.optim.Adam(groups, lr=0.0, eps=config.eps, betas=(config.beta1, config.beta2), fused=fused or None)


def exponential_lr(step: int, lr_init: float, lr_final: float, max_steps: int, delay_steps: int = 0,
                   delay_mult: float = 1.0) -> float:
    """log-linear from lr_init (step 0) to lr_final (step >= max_steps), times an optional sine warm-up."""
    if max_steps < 1:
        raise ValueError(f"max_steps: expected a positive integer, got {max_steps}")
    if lr_init == 0.0 and lr_final == 0.0:
        return 0.0
    t = min(max(step / max_steps, 0.0), 1.0)
    lr = math.exp(math.log(lr_init) * (1.0 - t) + math.log(lr_final) * t)
    if delay_steps > 0:
        lr *= delay_mult + (1.0 - delay_mult) * math.sin(0.5 * math.pi * min(max(step / delay_steps, 0.0), 1.0))
    return lr


def means_lr_at(step: int, config: OptimConfig, scene_extent: float, max_steps: int) -> float:
    extent = _check_extent(scene_extent)
    return exponential_lr(step, config.means_lr * extent, config.means_lr_final * extent,
                          config.means_lr_steps or max_steps,
                          config.means_lr_delay_steps, config.means_lr_delay_mult)


def update_learning_rates(optimizer: torch.optim.Optimizer, step: int, config: OptimConfig, scene_extent: float,
                          max_steps: int, lr_scale: float = 1.0, means_lr: Optional[float] = None) -> float:
    """Set the `means` group's lr for this step (call once per step before optimizer.step()); returns it.
    lr_scale: the batch's multiplier (train/scaling.py), applied on top of the schedule. means_lr: this step's lr
    in place of the schedule's (train.steps=auto's anneal, train/schedule.py), before lr_scale."""
    lr = means_lr_at(step, config, scene_extent, max_steps) if means_lr is None else means_lr
    if lr_scale != 1.0:
        lr *= lr_scale
    hit = False
    for group in optimizer.param_groups:
        if group.get("name") == "means":
            group["lr"] = lr
            hit = True
    if not hit:
        raise ValueError("optimizer: no param group named 'means' (build it with build_optimizer)")
    return lr


# ----- surgery -----------------------------------------------------------------------------------------------
def _optimizer_list(optimizers: Optimizers) -> list:
    if optimizers is None:
        return []
    if isinstance(optimizers, torch.optim.Optimizer):
        return [optimizers]
    if isinstance(optimizers, Mapping):
        return list(optimizers.values())
    return list(optimizers)


def _swap(optimizers: list, old: nn.Parameter, new: nn.Parameter, state_fn) -> None:
    """Point every group holding `old` at `new`; its state tensors shaped like `old` go through state_fn."""
    for opt in optimizers:
        for group in opt.param_groups:
            for j, q in enumerate(group["params"]):
                if q is old:
                    group["params"][j] = new
                    state = opt.state.pop(old, None)
                    if state:
                        # Per-row moments have the parameter's shape; scalars such as `step` are kept.
                        opt.state[new] = {k: state_fn(v) if torch.is_tensor(v) and v.shape == old.shape else v
                                          for k, v in state.items()}


def update_rows(model: GaussianModel, optimizers: Optimizers, keep: Optional[torch.Tensor] = None,
                append: Optional[Mapping[str, torch.Tensor]] = None) -> None:
    """Keep rows `keep` (bool mask [N] or index tensor) then append new rows (one tensor per parameter).

    Parameters and their optimizer moments stay aligned row by row; appended rows get zero moments.
    """
    optimizers = _optimizer_list(optimizers)
    n = model.num_primitives
    if keep is None:
        idx = torch.arange(n, device=model.device)
    else:
        keep = torch.as_tensor(keep, device=model.device)
        if keep.dtype == torch.bool:
            if keep.shape != (n,):
                raise ValueError(f"keep: expected a bool mask of shape [{n}], got {list(keep.shape)}")
            idx = keep.nonzero().squeeze(1)
        else:
            idx = keep.long()
    if append is not None:
        missing = [name for name in model.params if name not in append]
        extra = [name for name in append if name not in model.params]
        if missing or extra:
            raise ValueError(f"append: needs exactly the model's parameters; missing {missing}, unknown {extra}")
        counts = {name: t.shape[0] for name, t in append.items()}
        if len(set(counts.values())) > 1:
            raise ValueError(f"append: row counts differ between parameters: {counts}")
    for name, old in list(model.params.items()):
        def rows(t, _name=name, zero=False):
            kept = t[idx]
            if append is None:
                return kept
            add = append[_name].to(device=t.device, dtype=t.dtype)
            if add.shape[1:] != t.shape[1:]:
                raise ValueError(f"append[{_name!r}]: expected rows of shape {list(t.shape[1:])}, got {list(add.shape[1:])}")
            return torch.cat([kept, torch.zeros_like(add) if zero else add])

        new = nn.Parameter(rows(old.detach()), requires_grad=old.requires_grad)
        _swap(optimizers, old, new, lambda v, _rows=rows: _rows(v, zero=True))
        model.params[name] = new


def move_parameters(model: GaussianModel, optimizers: Optimizers, device) -> None:
    """Every parameter of `model` and its per-row optimizer state onto `device`, in place (scalars such as Adam's
    `step` stay where the optimizer keeps them)."""
    device = torch.device(device)
    for name, old in list(model.params.items()):
        if old.device != device:
            new = nn.Parameter(old.detach().to(device), requires_grad=old.requires_grad)
            _swap(_optimizer_list(optimizers), old, new, lambda v: v.to(device))
            model.params[name] = new


def set_param_values(model: GaussianModel, optimizers: Optimizers, name: str, values: torch.Tensor,
                     reset_state: bool = True) -> None:
    """Replace one parameter's values (same shape), zeroing its Adam moments (as 3DGS's opacity reset)."""
    if name not in model.params:
        raise ValueError(f"name: no parameter {name!r}; have {list(model.params)}")
    old = model.params[name]
    if values.shape != old.shape:
        raise ValueError(f"values: expected shape {list(old.shape)}, got {list(values.shape)}")
    new = nn.Parameter(values.detach().to(old.device, old.dtype).clone(), requires_grad=old.requires_grad)
    _swap(_optimizer_list(optimizers), old, new, torch.zeros_like if reset_state else (lambda v: v))
    model.params[name] = new


def copy_parameters(model: GaussianModel, optimizer: torch.optim.Optimizer, device="cpu", copy=None) -> dict:
    """A copy of every model parameter with its optimizer state (per-row moments and scalars such as `step`) on
    `device`: {name: {"value": tensor, "state": dict}}. load_parameters puts it back. copy(key, tensor), when
    given, makes each tensor's copy instead (key: (parameter name, "value" or the state's name); e.g.
    HostCopies.copy, train/host_copies.py)."""
    def one(key, v):
        if not torch.is_tensor(v):
            return v
        return copy(key, v) if copy is not None else v.detach().to(device, copy=True)
    return {name: {"value": one((name, "value"), p),
                   "state": {k: one((name, k), v) for k, v in optimizer.state.get(p, {}).items()}}
            for name, p in model.params.items()}


def load_parameters(model: GaussianModel, optimizers: Optimizers, saved: Mapping[str, dict]) -> None:
    """Replace every model parameter by its copy from copy_parameters (the row count may differ from the model's
    now) and its optimizer state by the copied state; each state tensor goes where that state lives now."""
    if set(saved) != set(model.params):
        raise ValueError(f"saved parameters {sorted(saved)} do not match the model's {sorted(model.params)}")
    for name, old in list(model.params.items()):
        value = saved[name]["value"]
        if value.shape[1:] != old.shape[1:]:
            raise ValueError(f"saved {name!r}: rows of shape {list(value.shape[1:])}, the model's are {list(old.shape[1:])}")
        new = nn.Parameter(value.to(old.device, old.dtype, copy=True), requires_grad=old.requires_grad)
        for opt in _optimizer_list(optimizers):
            if not any(q is old for group in opt.param_groups for q in group["params"]):
                continue
            now = opt.state.pop(old, {})
            _swap([opt], old, new, lambda v: v)  # the group now holds `new` (no state left to carry)
            state = {}
            for k, v in saved[name]["state"].items():
                if torch.is_tensor(v):  # Adam's `step` stays on the device its kernel keeps it on (fused: the GPU)
                    where = now[k].device if torch.is_tensor(now.get(k)) else (new.device if v.dim() else v.device)
                    v = v.to(where, copy=True)
                state[k] = v
            if state:
                opt.state[new] = state
        model.params[name] = new
