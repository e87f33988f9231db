"""One browser's frames, rendered on a thread of its own (no viser here: the server passes in callables).

While the camera moves, every move asks for a frame at the `moving` resolution; moves that arrive during a render
collapse into the newest, so a slow render never builds a backlog. Once the camera has been still for `settle`
seconds, one frame at the `still` resolution. While the model changes (live training), the still frame is
rendered again every `refresh` seconds, or every 4 times its render time if longer: a browser left open takes at
most a fifth of the time from training. A failed render is reported and the loop waits for the next move,
so a bad frame never takes down the process it lives in (the trainer's, with train.viewer=true).
"""
from __future__ import annotations

import sys
import threading
import time
import traceback
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from warpgs.viewer.camera import ViewerCamera, fit_size


@dataclass
class Resolution:
    """Longest image side while the camera moves and once it stops; shared by every client, set by the panel."""

    moving: int
    still: int


@dataclass
class FrameInfo:
    width: int
    height: int
    seconds: float
    still: bool


def to_uint8(rgb: torch.Tensor) -> np.ndarray:
    """[H, W, 3] float in [0, 1] -> uint8 numpy, rounded."""
    return (rgb.detach().clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


class FrameLoop:
    """`camera()` -> the client's current ViewerCamera; `render(camera, max_side)` -> [H, W, 3] float tensor;
    `send(image_uint8, info)` shows it; `version()` changes when the model does."""

    def __init__(self, camera: Callable[[], ViewerCamera], render: Callable[[ViewerCamera, int], torch.Tensor],
                 send: Callable[[np.ndarray, FrameInfo], None], resolution: Resolution, *,
                 version: Callable[[], int] = lambda: 0, settle: float = 0.25, refresh: float = 1.0,
                 name: str = "viewer"):
        self._camera, self._render, self._send, self._version = camera, render, send, version
        self.resolution, self.settle, self.refresh = resolution, float(settle), float(refresh)
        self._cond = threading.Condition()
        self._moved = False
        self._still_due = False
        self._last_move = 0.0
        self._still_version: Optional[int] = None
        self._still_time = 0.0
        self._still_seconds = 0.0
        self._stopped = False
        self.frames = 0
        self.stills = 0
        self.errors = 0
        self.last: Optional[FrameInfo] = None
        self._thread = threading.Thread(target=self._run, name=f"warpgs-{name}", daemon=True)
        self._thread.start()

    def moved(self) -> None:
        """The camera (or the canvas, or a setting) changed: draw a moving frame now, a still one later."""
        with self._cond:
            self._moved = True
            self._last_move = time.monotonic()
            self._cond.notify()

    def stop(self, timeout: Optional[float] = None) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify()
        if timeout is not None and threading.current_thread() is not self._thread:
            self._thread.join(timeout)

    # ----- the thread -----------------------------------------------------------------------------------------
    def _next(self) -> Optional[bool]:
        """Wait for the next frame to draw: True for a still frame, False for a moving one, None to stop."""
        with self._cond:
            while True:
                if self._stopped:
                    return None
                now = time.monotonic()
                if self._moved:
                    self._moved, self._still_due = False, True
                    return False
                wait = self.refresh
                if self._still_due:
                    left = self.settle - (now - self._last_move)
                    if left <= 0:
                        self._still_due = False
                        return True
                    wait = left
                elif self._still_version is not None and self._version() != self._still_version:
                    left = max(self.refresh, 4.0 * self._still_seconds) - (now - self._still_time)
                    if left <= 0:
                        return True
                    wait = left
                self._cond.wait(max(wait, 0.01))

    def _run(self) -> None:
        while True:
            still = self._next()
            if still is None:
                return
            try:
                self._draw(still)
            except Exception:  # reported, never raised: this thread may live in a training process
                self.errors += 1
                print(f"warpgs-view: a frame failed (the viewer goes on with the next camera move):\n"
                      f"{traceback.format_exc()}", file=sys.stderr)
                with self._cond:
                    self._still_due = False
                    self._still_version = None

    def _draw(self, still: bool) -> None:
        cam = self._camera()
        if cam.width <= 0 or cam.height <= 0:  # a hidden or collapsed canvas: nothing to show
            return
        res = self.resolution
        side = res.still if still else res.moving
        if not still and fit_size(cam.width, cam.height, res.moving) == fit_size(cam.width, cam.height, res.still):
            still = True  # the moving frame is already full size: it is the still one
            with self._cond:
                self._still_due = False
        version = self._version()
        t0 = time.perf_counter()
        image = to_uint8(self._render(cam, side))
        info = FrameInfo(image.shape[1], image.shape[0], time.perf_counter() - t0, still)
        self._send(image, info)
        self.frames += 1
        self.last = info
        if still:
            self.stills += 1
            self._still_version, self._still_time, self._still_seconds = version, time.monotonic(), info.seconds
