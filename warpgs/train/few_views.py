"""What few-view switches with an "auto" setting (train.virtual_views, train.drop_rate) share: "auto" turns the switch
on with at most a number of training views and off above, and the start line says which."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple


@dataclass(frozen=True)
class FewViewsRule:
    """train.<key>: "auto" is `on` with at most `most` training views, else 0; any other setting is taken as given.
    fewer: (views, value) pairs, in increasing views, that replace `on` with at most that many views (a rate measured
    at 3 views need not be the one measured at 4). what: the switch's name on the start line."""

    what: str
    key: str
    most: int
    on: float
    fewer: Tuple[Tuple[int, float], ...] = ()

    def value(self, setting, num_train_views: int, kind=float):
        """The setting's value (of `kind`) with this many training views."""
        if setting != "auto":
            return kind(setting)
        for views, value in self.fewer:
            if num_train_views <= views:
                return kind(value)
        return kind(self.on) if num_train_views <= self.most else kind(0)

    def note(self, setting, value, num_train_views: int, on_words: str) -> str:
        """The start line's words: `on_words` when on, why not when "auto" left it off, else ""."""
        if value:
            return on_words
        if setting == "auto":
            return (f"; {self.what} off (train.{self.key}=auto: {num_train_views} training views, on with at most "
                    f"{self.most})")
        return ""
