"""`train.viewer=true`: the browser viewer inside the training process, on the model being trained.

Read-only: frames render through `Trainer.render` under torch.no_grad while holding `trainer.lock`, which the
training loop holds over each step (warpgs/train/loop.py), so a frame never sees half a step and training does
exactly what it would without the viewer (tests/test_viewer.py compares the parameters). A frame does take time
from training: while a browser's camera moves, steps and frames alternate.
"""
from __future__ import annotations

import sys

from warpgs.viewer.deps import require_viser
from warpgs.viewer.turn_lock import TurnLock


def start_live_viewer(trainer, port: int, host: str = "127.0.0.1"):
    """Start serving `trainer`'s model; returns the Viewer (its `close()` stops it)."""
    require_viser("train.viewer=true")
    if not isinstance(port, int) or not 0 <= port <= 65535:
        raise ValueError(f"train.viewer_port: expected 0..65535 (0: any free port), got {port!r}")
    from warpgs.viewer.server import Viewer
    from warpgs.viewer.sources import TrainerSource

    # Between two steps the loop lets go of the lock for microseconds only: a lock that serves waiters in arrival
    # order is what gives a waiting frame its turn. Swapped in before training starts, while nobody holds it.
    if not isinstance(trainer.lock, TurnLock):
        trainer.lock = TurnLock()
    viewer = Viewer(TrainerSource(trainer), host=host, port=port, who="train.viewer=true")
    # Printed even with --quiet: without the address the viewer is of no use.
    print(f"warpgs: viewer at {viewer.url} (frames render between training steps)", file=sys.stderr, flush=True)
    return viewer
