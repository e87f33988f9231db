"""One Warp view of each torch CUDA stream, kept for the life of the process.

A `wp.Stream` made over a stream it does not own unregisters that stream when it is collected, and Warp keeps its
per-stream state by stream handle, shared by every view: unregistering destroys the stream's cached event and
frees its radix-sort scratch memory. A view made per call (as `wp.stream_from_torch` does) thus made the render's
next sort allocate its scratch again; on an H200 a training step with such an op took 6.45 ms against 4.88.
So every Warp launch on torch's streams goes through the one view here.
"""
from __future__ import annotations

import threading
from contextlib import contextmanager

import torch
import warp as wp

_VIEWS = {}
_LOCK = threading.Lock()


def warp_device(device: torch.device) -> wp.context.Device:
    if device.type == "cpu":
        return wp.get_device("cpu")
    return wp.get_device(f"cuda:{device.index if device.index is not None else torch.cuda.current_device()}")


def warp_stream(torch_stream) -> wp.Stream:
    """The Warp view of a torch CUDA stream (it keeps the torch stream, and so its handle, alive)."""
    key = (torch_stream.device.index, torch_stream.cuda_stream)
    view = _VIEWS.get(key)
    if view is None:
        with _LOCK:
            view = _VIEWS.get(key)
            if view is None:
                view = wp.Stream(warp_device(torch_stream.device), cuda_stream=torch_stream.cuda_stream)
                view._torch_stream = torch_stream
                _VIEWS[key] = view
    return view


@contextmanager
def on_torch_stream(device: torch.device):
    """Warp launches on `device` and, on CUDA, on torch's current stream there (no race with torch's kernels, and
    no cross-stream synchronisation: all the work is on that stream)."""
    with wp.ScopedDevice(warp_device(device)):
        if device.type != "cuda":
            yield
            return
        with wp.ScopedStream(warp_stream(torch.cuda.current_stream(device)), sync_enter=False):
            yield
