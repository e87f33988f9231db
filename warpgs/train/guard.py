"""The NaN guard: `NonFiniteError` and `NonFiniteGuard`, which names the first non-finite loss, gradient or
parameter among the tensors it is given."""
from __future__ import annotations

import dataclasses

from typing import Callable, Iterable, Optional, Sequence, Tuple

import torch

from warpgs.train.step_info import HostCopy

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
        _, _, norms = self._norms(result)
        if not all_finite(norms):  # raise_first finds nothing when only a sum overflowed (finite values, huge total)
            self.raise_first(step, result, lambda: self.first_nonfinite(grads=True))

    def raise_first(self, step: int, result, bad_gradient: Callable[[], Optional[str]]) -> None:
        """Raise NonFiniteError for the first offender, in this order: a parameter (an exact pass), the loss (naming
        its non-finite terms), a gradient (`bad_gradient()`'s name); nothing when none is found."""
        name = self.first_nonfinite(grads=False)
        if name is not None:
            raise NonFiniteError(step, name, f"parameter {name!r} is not finite")
        if result is not None and not bool(torch.isfinite(result.total.detach())):
            terms = [n for n, v in result.values.items() if not bool(torch.isfinite(v.detach()).all())]
            label = "/".join(terms) or "total"
            raise NonFiniteError(step, terms[0] if terms else "loss",
                                 f"loss {label} is not finite (all parameters are finite)")
        name = bad_gradient()
        if name is not None:
            raise NonFiniteError(step, name, f"gradient of {name!r} is not finite")

    def _norms(self, result) -> tuple:
        """(labels, tensors, norms): every non-empty parameter, then every non-empty gradient, labelled ("parameter"
        or "gradient", name), and their 1-norms, then the loss total's value labelled ("loss", "total")."""
        named = list(self.named_parameters())
        checked = ([(("parameter", n), p) for n, p in named if p.numel()]
                   + [(("gradient", n), p.grad) for n, p in named if p.grad is not None and p.grad.numel()])
        labels, tensors = [label for label, _ in checked], [t for _, t in checked]
        norms = _one_norms(tensors)
        if result is not None:
            labels.append(("loss", "total"))
            norms.append(result.total.detach().reshape(()).float())
        return labels, tensors, norms

    def flag(self, step: int, result=None) -> Optional[PendingCheck]:
        """check's test without its host read: a PendingCheck for the optimizers and a later read, or None when the
        tensors live on several devices (then call check)."""
        labels, tensors, norms = self._norms(result)
        if len({t.device for t in tensors}) > 1:
            return None
        if not norms:
            return None
        with torch.no_grad():
            flags = ~torch.isfinite(torch.stack(norms))
        return PendingCheck(step, labels, flags, result, self)

    def first_nonfinite(self, grads: bool) -> Optional[str]:
        """The first parameter (grads=False) or gradient (grads=True) holding a NaN or Inf, or None."""
        for name, p in self.named_parameters():
            t = p.grad if grads else p.detach()
            if t is not None and not bool(torch.isfinite(t).all()):
                return name
        return None


class PendingCheck:
    """One step's check computed on the device and read later (NonFiniteGuard.flag). `found_inf` (a 0-d float
    tensor, 1 when anything was not finite) is what fused Adam takes to skip that step on the device, so nothing
    non-finite is applied although the host did not wait for the backward; `raise_if_failed` reads the flags (by
    then a later sync has brought them to the host) and names the first offender in check's order: a parameter,
    then the loss, then a gradient. A gradient whose 1-norm overflows float32 counts as not finite here; a
    parameter's overflowing 1-norm alone (every value finite, their sum beyond float range) skips the step
    without an error, as check lets it pass."""

    def __init__(self, step: int, labels: list, flags: torch.Tensor, result, guard: "NonFiniteGuard"):
        # The loss's values only: held to the next step's check, its autograd graph would outlive the step.
        if dataclasses.is_dataclass(result):
            result = dataclasses.replace(result, total=result.total.detach())
        self.step, self.labels, self.result, self.guard = step, labels, result, guard
        self.found_inf = flags.any().float()
        self._flags = HostCopy(flags)

    def raise_if_failed(self) -> None:
        flags = self._flags.read()
        if not any(flags):
            return
        # The parameters and the loss are still there (the skipped step left the parameters as they were): named by
        # the exact passes; the gradients are gone, so their flags name them.
        grads = [name for (kind, name), f in zip(self.labels, flags) if f and kind == "gradient"]
        self.guard.raise_first(self.step, self.result, lambda: grads[0] if grads else None)


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


class StepGuard:
    """train.nan_guard around a training step's optimizer step. When every optimizer is fused Adam and the run is
    one process, the check is deferred: the step's PendingCheck makes Adam skip the step on the device if anything
    is not finite, and it is read (raising NonFiniteError for that step) at the next step's check or at `settle`,
    which a checkpoint calls first. A GPU step then needs no host read after its backward: the host goes on issuing
    the optimizer, densification and the next render while the backward runs. Otherwise the check is immediate
    (NonFiniteGuard.check)."""

    def __init__(self, guard: NonFiniteGuard):
        self.guard = guard
        self.pending: Optional[PendingCheck] = None

    @staticmethod
    def can_defer(optimizers: Sequence) -> bool:
        """Whether a deferred check can skip a step on the device: every optimizer is fused Adam."""
        return all(_fused_adam(o) for o in optimizers)

    def before_optimizers(self, step: int, result, optimizers: Sequence, *, defer: bool,
                          dropped: Sequence[torch.Tensor] = ()) -> None:
        """dropped: the step's renders' `pairs_overflowed` flags (speculative_pairs); a step with one set is skipped
        like a non-finite one, without an error (its renders were incomplete, not wrong in the model)."""
        self.settle()
        pending = self.guard.flag(step, result) if defer and self.can_defer(optimizers) else None
        if pending is None:
            self.guard.check(step, result)
            if dropped and any(bool(d) for d in dropped):  # read here: no deferred skip to ride on
                for opt in optimizers:
                    opt.zero_grad(set_to_none=True)
            return
        if dropped:
            with torch.no_grad():
                pending.found_inf = torch.stack([pending.found_inf] + [d.float() for d in dropped]).amax()
        for opt in optimizers:
            opt.found_inf = pending.found_inf  # Adam.step passes it to the fused kernel, which skips the update
        self.pending = pending

    @staticmethod
    def after_optimizers(optimizers: Sequence) -> None:
        """Take the flag off the optimizers, so no later step (the guard switched off, say) reads a stale one."""
        for opt in optimizers:
            opt.__dict__.pop("found_inf", None)

    def settle(self) -> None:
        """Read the deferred check, if any (raises NonFiniteError for its step)."""
        pending, self.pending = self.pending, None
        if pending is not None:
            pending.raise_if_failed()


def _fused_adam(opt) -> bool:
    return isinstance(opt, torch.optim.Adam) and bool(opt.defaults.get("fused"))
