"""The training views a Trainer draws from: device copies kept when data.preload (all of them loaded before the
first step, as 3DGS does), and a seeded order reshuffled every epoch. The order's generator and queue go into
checkpoints, so a resumed run draws the same views. The order is global (the same on every rank of a distributed
run), so any rank may render any view and each keeps them all."""
from __future__ import annotations

from typing import Dict, List

import torch


class TrainViews:
    """Owns the kept device views and the draw order (generator + the rest of this epoch's queue)."""

    def __init__(self, scene, device, *, seed: int, preload: bool = True):
        self.scene = scene
        self.device = torch.device(device)
        self.preload = bool(preload)
        self.indices: List[int] = list(scene.train)
        self.generator = torch.Generator().manual_seed(int(seed))
        self.queue: List[int] = []
        self._kept: Dict[int, object] = {}

    def view(self, index: int):
        """Scene view `index` on the device (kept for the next call when preloading)."""
        if index not in self._kept:
            v = self.scene.view(index, self.device)
            if not self.preload:
                return v
            self._kept[index] = v
        return self._kept[index]

    def load_all(self) -> int:
        """With preload, every training view onto the device now: step times then time steps (a first draw of each
        view no longer reads its image mid-run), and a bad image stops the run before step 1. Returns how many views
        were loaded (0 without preload, or when all were kept already)."""
        if not self.preload:
            return 0
        missing = [i for i in self.indices if i not in self._kept]
        for i in missing:
            self.view(i)
        return len(missing)

    def kept_or_new(self, index: int):
        """The kept copy when there is one, else a fresh view that is not kept (for evaluation)."""
        return self._kept[index] if index in self._kept else self.scene.view(index, self.device)

    def next(self):
        """The next training view: a new random permutation of the training views each epoch."""
        return self.view(self.draw(1)[0])

    def draw(self, n: int) -> List[int]:
        """The scene indices of the next n training views, not loaded. A batch that crosses an epoch's end takes
        the rest of that epoch and the start of the next (so a view can appear twice in it). Every rank of a
        distributed run draws the whole global batch from the same seeded order and loads only its own slice."""
        if not self.indices:
            raise ValueError(f"scene: {getattr(self.scene, 'root', 'the scene')} has no training views to draw")
        out = []
        for _ in range(int(n)):
            if not self.queue:
                self.queue = torch.randperm(len(self.indices), generator=self.generator).tolist()
            out.append(self.indices[self.queue.pop(0)])
        return out

    # The checkpoint keys of checkpoints written before this class existed.
    def state_dict(self) -> dict:
        return {"view_generator": self.generator.get_state(), "view_queue": list(self.queue)}

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["view_generator"])
        self.queue = list(state["view_queue"])
