"""The training views a Trainer draws from: device copies kept when data.preload (all of them loaded before the
first step, as 3DGS does, decoded in up to LOAD_THREADS threads), and a seeded order reshuffled every epoch. The
order's generator and queue go into checkpoints, so a resumed run draws the same views. The order is global (the
same on every rank of a distributed run), so any rank may render any view and each keeps them all. Kept images
from 8-bit files are held as their 8-bit codes (`data/compact_image.py`: a quarter of the memory) and expanded,
bit for bit, when a view is drawn. With
train.steps=auto some training views are held out for validation (`hold_out`) and may come back for the run's last
steps (`restore_held_out`); the current training list goes into checkpoints too."""
from __future__ import annotations

import copy
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Dict, List

import torch

from warpgs.data import compact_image

LOAD_THREADS = 8  # views decoded at once by load_all (image decoding releases the GIL)


class TrainViews:
    """Owns the kept device views and the draw order (generator + the rest of this epoch's queue)."""

    def __init__(self, scene, device, *, seed: int, preload: bool = True):
        self.scene = scene
        self.device = torch.device(device)
        self.preload = bool(preload)
        self.indices: List[int] = list(scene.train)
        self.generator = torch.Generator().manual_seed(int(seed))
        self.queue: List[int] = []
        self.held_out: List[int] = []  # training views kept out of the draws (train.steps=auto's validation)
        self._split = False  # whether views were ever held out
        self._kept: Dict[int, object] = {}

    def hold_out(self, indices) -> None:
        """Take these training views out of the draws (before the first draw: the queue holds positions)."""
        held = [int(i) for i in indices]
        missing = [i for i in held if i not in self.indices]
        if missing:
            raise ValueError(f"hold_out: views {missing} are not training views")
        if self.queue:
            raise RuntimeError("hold_out: only before the first draw")
        self.held_out, self._split = held, True
        held_set = set(held)
        self.indices = [i for i in self.indices if i not in held_set]

    def restore_held_out(self) -> List[int]:
        """Put the held-out views back into the draws (from the next epoch: the rest of this one stays as drawn).
        Returns them."""
        back, self.held_out = self.held_out, []
        self.indices = self.indices + back
        return back

    def view(self, index: int):
        """Scene view `index` on the device (kept for the next call when preloading)."""
        if index not in self._kept:
            if not self.preload:
                return self.scene.view(index, self.device)
            with torch.inference_mode(False):  # kept for training steps: never inference tensors
                self._kept[index] = _compact(self.scene.view(index, self.device))
        return _expanded(self._kept[index])

    def load_all(self) -> int:
        """With preload, every training view onto the device now: step times then time steps (a first draw of each
        view no longer reads its image mid-run), and a bad image stops the run before step 1. Returns how many views
        were loaded (0 without preload, or when all were kept already)."""
        if not self.preload:
            return 0
        missing = [i for i in self.indices + self.held_out if i not in self._kept]
        if not missing:
            return 0
        device = self.device
        if device.type == "cuda" and device.index is None:  # a worker thread's current device is its own
            device = torch.device("cuda", torch.cuda.current_device())
        threads = min(LOAD_THREADS, os.cpu_count() or 1, len(missing))
        with ThreadPoolExecutor(threads) as pool:  # the first bad image raises here, naming its file
            for i, v in zip(missing, pool.map(lambda i: _compact(self.scene.view(i, device)), missing)):
                self._kept[i] = v
        return len(missing)

    def kept_or_new(self, index: int):
        """The kept copy when there is one, else a fresh view that is not kept (for evaluation)."""
        return _expanded(self._kept[index]) if index in self._kept else self.scene.view(index, self.device)

    def kept_bytes(self) -> int:
        """Bytes of the kept views' images (as kept: 8-bit codes where they could be)."""
        return sum(v.image.numel() * v.image.element_size() for v in self._kept.values())

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

    # The checkpoint keys of checkpoints written before this class existed, plus the drawn and held-out lists.
    # (the lists only in runs that held views out, so other checkpoints keep their keys).
    def state_dict(self) -> dict:
        state = {"view_generator": self.generator.get_state(), "view_queue": list(self.queue)}
        if self._split:
            state.update(view_indices=list(self.indices), view_held_out=list(self.held_out))
        return state

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["view_generator"])
        self.queue = list(state["view_queue"])
        split = self._split  # this run holds views out (train.steps=auto)
        if self._split and "view_indices" not in state:
            raise ValueError("train.steps=auto: the checkpoint was written by a run that drew every training view "
                             "(a step count); resume it with that step count, or start the auto run afresh")
        if "view_indices" in state:  # older checkpoints: every training view was drawn
            self.indices = list(state["view_indices"])
            self.held_out, self._split = list(state.get("view_held_out", [])), True
            if not split:  # an auto run's checkpoint resumed with a step count: no validation, so every view
                self.restore_held_out()  # is drawn (appended: the queue's positions stay valid)


def _compact(view):
    """The view to keep: its image as 8-bit codes when it is exactly an 8-bit image (else the view itself)."""
    codes = compact_image.pack(view.image)
    if codes is None:
        return view
    kept = copy.copy(view)
    kept.image = codes
    return kept


def _expanded(kept):
    """A kept view as the loader made it (a shallow copy with the float image; the other tensors are shared)."""
    if kept.image.dtype != torch.uint8:
        return kept
    view = copy.copy(kept)
    view.image = compact_image.unpack(kept.image)
    return view
