"""The NaN guard: `NonFiniteError` and `NonFiniteGuard`, which names the first non-finite loss, gradient or
parameter among the tensors it is given."""
from __future__ import annotations

from typing import Callable, Iterable, Optional, Sequence, Tuple

import torch

NamedTensors = Callable[[], Iterable[Tuple[str, torch.Tensor]]]


class NonFiniteError(FloatingPointError):
    """Training produced NaN/Inf; `step` and `name` (the first offending parameter or loss term) say where."""

    def __init__(self, step: int, name: str, problem: str):
        self.step, self.name = step, name
        super().__init__(f"step {step}: {problem}")


class NonFiniteGuard:
    """Checks the parameters `named_parameters()` yields (asked anew at every check, so primitives added or pruned
    since are seen) and their gradients. Holds no other state."""

    def __init__(self, named_parameters: NamedTensors):
        if not callable(named_parameters):
            raise ValueError(f"named_parameters: expected a callable yielding (name, tensor), got {named_parameters!r}")
        self.named_parameters = named_parameters

    def check(self, step: int, result=None) -> None:
        """Raise NonFiniteError unless the loss (`result.total`, a LossResult), every gradient and every parameter
        are finite. Cheap on the good path: the 1-norm of every tensor (NaN and Inf propagate through it; one
        multi-tensor launch per device and dtype) and one sync per device; the names come from a second, exact pass
        only when a norm is not finite. Parameters are checked too because an invisible NaN primitive has zero
        gradient and would otherwise reach a checkpoint unnoticed. The tensors may live on several devices (a
        model-parallel checkpoint: the model gathered in CPU memory, the modules on the GPU): each device's norms
        are combined there."""
        named = list(self.named_parameters())
        tensors = [p for _, p in named if p.numel()] + [p.grad for _, p in named
                                                        if p.grad is not None and p.grad.numel()]
        sums = _one_norms(tensors)
        if result is not None:
            sums.append(result.total.detach().reshape(()).float())
        if all_finite(sums):
            return
        name = self.first_nonfinite(grads=False)
        if name is not None:
            raise NonFiniteError(step, name, f"parameter {name!r} is not finite")
        if result is not None and not bool(torch.isfinite(result.total.detach())):
            terms = [n for n, v in result.values.items() if not bool(torch.isfinite(v))]
            label = "/".join(terms) or "total"
            raise NonFiniteError(step, terms[0] if terms else "loss",
                                 f"loss {label} is not finite (all parameters are finite)")
        name = self.first_nonfinite(grads=True)
        if name is not None:
            raise NonFiniteError(step, name, f"gradient of {name!r} is not finite")
        # Only a sum overflowed (finite values beyond float range in total): nothing is actually non-finite.

    def first_nonfinite(self, grads: bool) -> Optional[str]:
        """The first parameter (grads=False) or gradient (grads=True) holding a NaN or Inf, or None."""
        for name, p in self.named_parameters():
            t = p.grad if grads else p.detach()
            if t is not None and not bool(torch.isfinite(t).all()):
                return name
        return None


def _one_norms(tensors: Sequence[torch.Tensor]) -> list:
    """The 1-norm of each tensor as a float32 0-d tensor on its device, one multi-tensor launch per device and dtype
    (a sum per tensor was a launch each: on a GPU that is host time on every step)."""
    groups = {}
    for t in tensors:
        groups.setdefault((t.device, t.dtype), []).append(t)
    with torch.no_grad():
        return [n.float() for group in groups.values() for n in torch._foreach_norm(group, 1)]


def all_finite(scalars: Sequence[torch.Tensor]) -> bool:
    """Whether every 0-d tensor is finite: one stack and one read-back per device they are on."""
    by_device = {}
    for s in scalars:
        by_device.setdefault(s.device, []).append(s)
    return all(bool(torch.isfinite(torch.stack(group)).all()) for group in by_device.values())
