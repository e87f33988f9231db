"""StepInfo: what Trainer.train_step returns, a dict whose loss values are read from the device on first use."""
from __future__ import annotations

from typing import Callable, Optional

LAZY_KEYS = ("loss", "values", "psnr")


class StepInfo(dict):
    """A step's info (step, loss, values, psnr, num_primitives, densify, view, views, stop). "loss", "values" and
    "psnr" are filled in from `read` (the views' HostScalars, train/batch.py) the first time any of them is asked
    for, or the info is iterated, copied or printed: on a GPU that waits for the step's backward, so the training
    loop reads them a step later, when they are on the host already (a GPU profile at 870k Gaussians: 6.3 ms a
    step without the read at the end of the step against 7.2 ms with it). Every other key is a plain value."""

    def __init__(self, items: dict, read: Optional[Callable[[], dict]] = None,
                 ready: Optional[Callable[[], bool]] = None):
        super().__init__(items)
        self._read, self._ready = read, ready

    @property
    def pending(self) -> bool:
        """Whether the loss values are still on their way (reading one of them now would wait for the device)."""
        return self._read is not None and not (self._ready is not None and self._ready())

    def read(self) -> "StepInfo":
        """Fill in the loss values now (on a GPU: waits for them, once)."""
        if self._read is not None:
            read, self._read = self._read, None
            dict.update(self, read())
        return self

    def __getitem__(self, key):
        if key in LAZY_KEYS:
            self.read()
        return dict.__getitem__(self, key)

    def get(self, key, default=None):
        if key in LAZY_KEYS:
            self.read()
        return dict.get(self, key, default)

    def __contains__(self, key) -> bool:
        return key in LAZY_KEYS or dict.__contains__(self, key)

    def __iter__(self):
        return dict.__iter__(self.read())

    def __len__(self) -> int:
        return dict.__len__(self.read())

    def keys(self):
        return dict.keys(self.read())

    def values(self):
        return dict.values(self.read())

    def items(self):
        return dict.items(self.read())

    def copy(self) -> dict:
        return dict(self.read())

    def __eq__(self, other) -> bool:
        return dict.__eq__(self.read(), other)

    __hash__ = None  # as dict's

    def __repr__(self) -> str:
        return dict.__repr__(self.read())
