"""Per (thread, device, torch stream) state of the render ops: the Warp device and the Warp view of torch's stream,
the workspace (render/workspace.py: scratch buffers, recorded launches, CUDA graphs), descriptors and array views of
tensors memoised by address, and the buffer each call's camera is copied into (`staged_together`)."""
from __future__ import annotations

import threading
from typing import Dict

import torch
import warp as wp

from warpgs.render.torch_streams import warp_device, warp_stream
from warpgs.render.workspace import Workspace


class DeviceState:
    """Per (thread, device, torch stream): the Warp device, the Warp view of torch's stream, the workspace."""

    def __init__(self, device: torch.device, torch_stream, key=None):
        self.device = device
        self.key = key  # in this thread's table: (device index, stream handle) on GPUs, None on the CPU
        self.wdev = warp_device(device)
        self.stream = None if torch_stream is None else warp_stream(torch_stream)  # one view per stream
        self.ws = Workspace(self.wdev)
        if torch_stream is not None:
            self.ws.graphs.stream_factory = lambda: _nonblocking_stream(device, self.wdev)
        self._descs: Dict = {}
        self._arrays: Dict = {}
        self._staged: Dict = {}

    def desc(self, t: torch.Tensor, dtype):
        """`_desc(t, dtype)`, memoised by address, shape and strides (all a descriptor holds): the same memory seen
        again (parameters updated in place, torch's allocator handing back a block) gives the same object, which
        a recorded launch then does not re-pack."""
        key = (t.data_ptr(), t.shape, t.stride(), dtype)
        d = self._descs.get(key)
        if d is None:
            if len(self._descs) > _MEMO_SIZE:
                self._descs.clear()
            d = self._descs[key] = _desc(t, dtype)
        return d

    def staged_together(self, parts) -> list:
        """Small float32 tensors of this device (a render's camera: viewmat, intrinsics, K, background) copied, in one
        concatenation, into this state's own buffer for their shapes (made once, then rewritten in stream order).
        A render's camera changes every training step; read from a fixed buffer it leaves the launch sequence's key
        (workspace.LaunchSequence) unchanged, so the sequence replays from its CUDA graph. Returns views of the
        buffer shaped like `parts`, the same view objects every call (their descriptors memoise)."""
        layout = tuple(tuple(t.shape) for t in parts)
        hit = self._staged.get(layout)
        if hit is None:
            numels = [t.numel() for t in parts]
            with torch.inference_mode(False):  # made under inference_mode, a later render outside it could not write it
                buf = torch.empty(sum(numels), dtype=torch.float32, device=parts[0].device)
            views, at = [], 0
            for shape, k in zip(layout, numels):
                views.append(buf[at: at + k].view(shape))
                at += k
            hit = self._staged[layout] = (buf, views)
        flat = [t.reshape(-1) for t in parts]
        if torch.is_grad_enabled():  # the values only: a copy that autograd records would chain every render's graph
            with torch.no_grad():
                torch.cat(flat, out=hit[0])
        else:
            torch.cat(flat, out=hit[0])
        return hit[1]

    def tensor(self, a: wp.array) -> torch.Tensor:
        """wp.to_torch(a), memoised like `desc` (for workspace views read every call)."""
        key = ("tensor", a.ptr, a.shape, a.dtype)
        t = self._descs.get(key)
        if t is None:
            if len(self._descs) > _MEMO_SIZE:
                self._descs.clear()
            t = self._descs[key] = wp.to_torch(a, requires_grad=False)
        return t

    def array(self, t: torch.Tensor, n: int, dtype) -> wp.array:
        """A Warp array of n elements over a tensor's memory, memoised like `desc`."""
        return self.array_at(t.data_ptr(), n, dtype)

    def array_at(self, ptr: int, n: int, dtype) -> wp.array:
        """`array` from an address (memory a caller keeps alive, e.g. part of a block before its torch views exist)."""
        key = (ptr, n, dtype)
        a = self._arrays.get(key)
        if a is None:
            if len(self._arrays) > _MEMO_SIZE:
                self._arrays.clear()
            a = self._arrays[key] = wp.array(ptr=ptr, dtype=dtype, shape=(n,), device=self.wdev)
        return a

    def scope(self):
        """Makes torch's stream Warp's current one (no cross-stream sync: all our work is on torch's stream)."""
        if self.stream is None:
            return _NULL_SCOPE
        return wp.ScopedStream(self.stream, sync_enter=False)


def _nonblocking_stream(device: torch.device, wdev) -> wp.Stream:
    """A Warp view of a new non-blocking CUDA stream (torch makes its streams non-blocking), where graphs are
    captured: a blocking one would make other threads' work on the legacy default stream fail during a capture."""
    side = torch.cuda.Stream(device)
    stream = wp.Stream(wdev, cuda_stream=side.cuda_stream)
    stream._torch_stream = side  # keeps torch's stream (and so its handle) alive
    return stream


class _NullScope:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


_NULL_SCOPE = _NullScope()
_MEMO_SIZE = 256  # descriptors and array views kept per device state
_local = threading.local()


def device_state(device: torch.device) -> DeviceState:
    table: Dict = getattr(_local, "table", None)
    if table is None:
        table = _local.table = {}
    stream = None
    if device.type == "cuda":
        if device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
        stream = torch.cuda.current_stream(device)
        key = (device.index, stream.cuda_stream)
    else:
        key = None
    state = table.get(key)
    if state is None:
        state = table[key] = DeviceState(device, stream, key)
    return state


def backward_state(forward: DeviceState) -> DeviceState:
    """This thread's state for the device and stream of a forward's state: what that render's backward uses.
    Autograd runs a backward on its forward's stream, so the forward's key is the backward's: no asking torch for the
    current device and stream, which on autograd's CUDA worker thread is ~20 µs of a 100k render's host time."""
    table = getattr(_local, "table", None)
    state = None if table is None else table.get(forward.key)
    return state if state is not None else device_state(forward.device)


def release_workspaces() -> None:
    """Frees this thread's workspaces: scratch memory, lent buffer sets not in use, recorded launches. The next
    render allocates them again."""
    _local.table = {}


def _desc(t: torch.Tensor, dtype):
    """A bare Warp array descriptor of a contiguous tensor, holding no reference to it (torch keeps the memory
    alive for the call; a recorded launch must not keep it alive afterwards)."""
    d = wp.from_torch(t, dtype=dtype, requires_grad=False, return_ctype=True)
    d._ref = None
    d._gradref = None
    return d
