"""The loss terms of a run: resolved from the config's `losses`, the render outputs they need (over the whole run,
and at one step when schedules switch terms off), and their weighted sum."""
from __future__ import annotations

import difflib
from typing import Iterable, Sequence

from warpgs.losses import compute_losses, registered_losses, required_outputs, resolve_losses


def resolve_terms(losses: dict) -> list:
    """The LossTerms a config's `losses` names; an unknown name gets the registered ones and a close match."""
    try:
        return resolve_losses(losses)
    except ValueError as e:
        msg = str(e)
        if "unknown loss" in msg:
            name = msg.split(":", 1)[0].replace("losses.", "")
            close = difflib.get_close_matches(name, registered_losses(), n=1, cutoff=0.5)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ValueError(f"losses.{name}: unknown loss; registered: {registered_losses()} (register your own "
                             f"with warpgs.register_loss and list its module under `imports`){hint}") from None
        raise


class LossSet:
    """Immutable once built: the terms, the outputs rendered besides theirs (`always`, e.g. the extensions'), and
    `outputs`, the union over the whole run."""

    def __init__(self, terms: Iterable, *, always: Sequence[str] = ()):
        self.terms = list(terms)
        self.always = list(always)
        self.outputs = required_outputs(self.terms, always=self.always)

    @property
    def names(self) -> list:
        return [t.name for t in self.terms]

    def outputs_at(self, step: int, max_steps: int) -> tuple:
        """The outputs to render at this step: those of the terms whose scheduled weight is not 0 now, plus
        `always` (the union when no term has a schedule)."""
        if all(t.schedule is None for t in self.terms):
            return self.outputs
        live = [t for t in self.terms if t.weight_at(step, max_steps) > 0]
        return required_outputs(live, always=self.always)

    def __call__(self, render_out, batch, model, step: int, max_steps: int):
        """LossResult: the differentiable weighted total and the unweighted value of every term computed."""
        return compute_losses(self.terms, render_out, batch, model, step, max_steps)
