"""What settings with an "auto" that depends on the training-view count (train.virtual_views, train.drop_rate,
model.prior_points_confidence, strategy.unpool_every) share: "auto" is one value with at most a number of training
views and another above (off, for the few-view switches; unpooling the other way round), with other values below a
few smaller counts if measured so (dropout: on with few views and with many, off between), and the start line says
which. The count is the scene's training views (scene.train), train.steps=auto's held-out validation views included:
the priors and initial points are made from all of them, and they train again in its polish (schedule.polish)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple


@dataclass(frozen=True)
class FewViewsRule:
    """key (the config key, e.g. "train.drop_rate"): "auto" is `on` with at most `most` training views, else `more`
    (0: off); any other setting is taken as given. fewer: (views, value) pairs, in increasing views, that replace `on`
    with at most that many views (a rate measured at 3 views need not be the one measured at 4). what: the switch's
    name on the start line."""

    what: str
    key: str
    most: int
    on: float
    fewer: Tuple[Tuple[int, float], ...] = ()
    more: float = 0

    def value(self, setting, num_train_views: int, kind=float):
        """The setting's value (of `kind`) with this many training views."""
        if setting != "auto":
            return kind(setting)
        for views, value in self.fewer:
            if num_train_views <= views:
                return kind(value)
        return kind(self.on) if num_train_views <= self.most else kind(self.more)

    def note(self, setting, value, num_train_views: int, on_words: str) -> str:
        """The start line's words: `on_words` when on, why not when "auto" left it off, else ""."""
        if value:
            return on_words
        if setting == "auto":
            return f"; {self.what} off ({self.key}=auto: {num_train_views} training views, on with {self.when_on()})"
        return ""

    def when_on(self) -> str:
        """The view counts at which "auto" is on, in words ("at most 4", "more than 9", "at most 4 or more than 9")."""
        if self.on and self.more:
            return "any number"
        most_on = max([views for views, value in self.fewer if value] + ([self.most] if self.on else []), default=0)
        parts = ([f"at most {most_on}"] if most_on else []) + ([f"more than {self.most}"] if self.more else [])
        return " or ".join(parts)
