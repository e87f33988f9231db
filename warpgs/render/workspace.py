"""What a render call keeps between calls, to cut its fixed host cost (torch-free).

At 100k Gaussians a GPU render is mostly host work: every `wp.launch` re-packs its arguments, every `wp.zeros`
allocates and clears memory, every wrapper builds a descriptor. Three things here avoid most of that:

- `Workspace`: scratch arrays kept per (device, stream, thread) and grown geometrically, handed out as views of
  the size a call needs, for buffers that live within one call (sort keys, prefix sums, tile rectangles, ...).
  What a backward pass reads later comes from a `FrameLease`: a set of buffers lent to one render and returned
  to the pool only when that render's autograd context lets go of it, so a buffer is never overwritten while a
  graph still needs it.
- `LaunchCache`: one recorded `wp.Launch` per launch site; a call updates only the parameters that changed since
  the last one (workspace views keep their descriptor objects, so they are skipped by identity) and replays it.
- `LaunchSequence`: the launches up to a render's one host sync (or, speculative, with no sync: `run_unwaited`; or
  read later, while the GPU works on what was queued after: `run_deferred`), issued together; on a GPU they become
  one CUDA graph once the same sequence (same arrays, sizes and scalars) comes a second time (graph_cache.py).

`benchmarks/micro_overhead.py` measures the pieces (CPU, this machine): `wp.launch` with 23 arguments 22 us
against 5 us for a replay, `set_param_at_index` 0.7 us, `wp.from_torch` 4.5 us (1.8 us as a bare descriptor).
"""
from __future__ import annotations

import threading
from typing import Dict, Tuple

import warp as wp

from warpgs.render.graph_cache import GraphCache
from warpgs.render.pair_room import PairRooms

GROWTH = 1.25  # capacity grows to this multiple of the first size that does not fit
# Recording a launch loads the kernel's module on first use. Two threads loading a module at once crashed Warp 1.19
# on the CPU (reproduced with two threads each recording a launch of one kernel for the first time), so recording is
# serialised; replays run concurrently (the CPU blend runs one replay per thread).
_RECORD_LOCK = threading.Lock()


class LaunchCache:
    """Recorded launches keyed by launch site. `launch` takes the same arguments as `wp.launch` (inputs and outputs
    as one list) and re-packs only the parameters that differ from the previous call at that site.

    Parameters are compared by identity (arrays, descriptors, structs) or value (Python scalars). The cache keeps
    the previous arguments' descriptors (never the arrays' memory), so a freed descriptor can never be mistaken
    for a live one."""

    def __init__(self, device):
        self.device = device
        self._entries: Dict[object, list] = {}

    def launch(self, key, kernel, dim: int, args, block_dim: int = 0) -> None:
        if dim > 0:
            self.launch_params(key, kernel, dim, [a.__ctype__() if isinstance(a, _ARRAY) else a for a in args],
                               block_dim)

    def launch_params(self, key, kernel, dim: int, params: list, block_dim: int = 0) -> None:
        """`launch` with the arguments already as parameters (see _ARRAY; what LaunchSequence stores)."""
        entry = self._entries.get(key)
        if entry is None or entry[0] is not kernel:
            with _RECORD_LOCK:
                cmd = wp.launch(kernel, dim=dim, inputs=params, device=self.device, block_dim=block_dim or None,
                                record_cmd=True)
            entry = self._entries[key] = [kernel, cmd, list(params), dim]  # a copy: the caller's list stays as given
        else:
            cmd, prev = entry[1], entry[2]
            for i, a in enumerate(params):  # runs for every argument of every launch: kept inline
                b = prev[i]
                if a is b:
                    continue
                t = type(a)
                if (t is int or t is float) and type(b) is t and a == b:
                    continue
                cmd.set_param_at_index(i, a)
                prev[i] = a
            if dim != entry[3]:
                cmd.set_dim(dim)
                entry[3] = dim
        entry[1].launch()

    def launch_adjoint(self, key, kernel, dim: int, args, adj_args, block_dim: int = 0) -> None:
        """The generated adjoint of `kernel` (what wp.Tape.backward would launch): `adj_args` are the gradient
        arrays of `args` (None where there is none, 0 for scalars)."""
        if dim <= 0:
            return
        args = [a.__ctype__() if isinstance(a, _ARRAY) else a for a in args]
        adj_args = [a.__ctype__() if isinstance(a, _ARRAY) else a for a in adj_args]
        entry = self._entries.get(key)
        if entry is None or entry[0] is not kernel:
            with _RECORD_LOCK:
                cmd = wp.launch(kernel, dim=dim, inputs=args, adj_inputs=adj_args, device=self.device, adjoint=True,
                                block_dim=block_dim or None, record_cmd=True)
            entry = self._entries[key] = [kernel, cmd, args, dim, adj_args]
        else:
            cmd = entry[1]
            for adjoint, params, prev in ((False, args, entry[2]), (True, adj_args, entry[4])):
                for i, a in enumerate(params):
                    b = prev[i]
                    if a is b or (type(a) in _BY_VALUE_NUMBERS and type(b) is type(a) and a == b):
                        continue
                    cmd.set_param_at_index(i, a, adjoint=adjoint)
                    prev[i] = a
            if dim != entry[3]:
                cmd.set_dim(dim)
                entry[3] = dim
        entry[1].launch()


# Launch arguments become parameters: arrays travel as their (cached) descriptors, `a.__ctype__() if isinstance(a,
# _ARRAY) else a` (written out where launches are built: it runs for every argument), so identity then means
# 'same array view'.
_ARRAY = wp.array


_BY_VALUE_NUMBERS = (int, float)  # launch parameters that match by value (the rest by identity)


class Buffers:
    """Named arrays of one device, grown geometrically and handed out as views of the size a call needs. A view
    object (and so its descriptor) is reused while the size stays the same, which is what lets `LaunchCache` skip
    re-packing it."""

    def __init__(self, device):
        self.device = wp.get_device(device)
        self._buffers: Dict[str, wp.array] = {}
        self._views: Dict[str, Tuple[object, wp.array]] = {}

    def array(self, name: str, n: int, dtype) -> wp.array:
        """A view of n elements (at least 1) of the named buffer. Contents are whatever the last user left."""
        n = max(int(n), 1)
        view = self._views.get(name)
        if view is not None and view[0] == (n, dtype):
            return view[1]
        buf = self._buffers.get(name)
        if buf is None or buf.dtype != dtype or buf.shape[0] < n:
            old = 0 if buf is None or buf.dtype != dtype else buf.shape[0]
            cap = n if old == 0 else max(n, int(old * GROWTH) + 1)
            buf = self._buffers[name] = wp.empty(cap, dtype=dtype, device=self.device)
        v = buf if buf.shape[0] == n else buf[:n]
        self._views[name] = ((n, dtype), v)
        return v

    __call__ = array  # a Buffers object is a `keep` allocator

    def view(self, name: str, base: wp.array, offset: int, shape, dtype) -> wp.array:
        """A typed view of `base` (a float32 buffer) from element `offset` on, reused while nothing changes."""
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        key = (base.ptr, offset, shape, dtype)
        hit = self._views.get(name)
        if hit is not None and hit[0] == key:
            return hit[1]
        v = wp.array(ptr=base.ptr + 4 * offset, dtype=dtype, shape=shape, device=self.device)
        self._views[name] = (key, v)
        return v


class FrameLease:
    """A set of `Buffers` lent to one render for what its backward reads. The set goes back to the workspace's pool
    when the lease is dropped (the torch op holds it in its autograd context, so: after the backward, or when the
    graph is freed unused); only then can another render get it. So a buffer is never reused while a graph that
    needs it is alive, and steady training (render, backward, render, ...) gets the same buffers every step."""

    def __init__(self, pool: list, buffers: Buffers):
        self._pool = pool
        self.buffers = buffers

    def __call__(self, name: str, n: int, dtype) -> wp.array:
        return self.buffers.array(name, n, dtype)

    def __del__(self):
        try:
            self._pool.append(self.buffers)
        except Exception:  # interpreter shutdown
            pass


class Workspace(Buffers):
    """Scratch arrays of one device (and stream and thread), reused by every call, plus the recorded launches and
    the pool of per-render buffer sets (`lease_frame`)."""

    def __init__(self, device):
        super().__init__(device)
        self.launches = LaunchCache(self.device)
        self._cache: Dict[object, object] = {}  # small per-workspace memo (structs, dummies, host buffers)
        self._free_frames: list = []
        self._host_views: Dict[int, tuple] = {}
        self.graphs = GraphCache(self.device)
        self.pair_rooms = PairRooms()  # where renders with speculative_pairs size their pair sort (pair_room.py)

    def sequence(self, immediate: bool = False) -> "LaunchSequence":
        """An empty launch sequence on this workspace (see LaunchSequence)."""
        return LaunchSequence(self, immediate)

    def lease_frame(self) -> FrameLease:
        """Buffers for one render whose backward will follow (see FrameLease)."""
        buffers = self._free_frames.pop() if self._free_frames else Buffers(self.device)
        return FrameLease(self._free_frames, buffers)

    def memo(self, key, make):
        """A value made once per workspace (e.g. a 1-element dummy array, a pinned host buffer)."""
        value = self._cache.get(key)
        if value is None:
            value = self._cache[key] = make()
        return value

    def zeros(self, name: str, shape, dtype) -> wp.array:
        """A zero-filled array that nobody writes (e.g. the upstream gradient of an output the loss did not use),
        filled once per size."""
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        return self.memo(("zeros", name, shape, dtype), lambda: wp.zeros(shape, dtype=dtype, device=self.device))

    def dummy(self, dtype, ndim: int = 1) -> wp.array:
        """A zeroed 1-element array for arguments a kernel never reads (outputs not asked for)."""
        return self.memo(("dummy", dtype, ndim),
                         lambda: wp.zeros((1,) * ndim, dtype=dtype, device=self.device))

    def host_view(self, a: wp.array):
        """a.numpy() of a host array, kept while the same array object comes back (a workspace view does)."""
        views = self._host_views
        hit = views.get(id(a))
        if hit is None or hit[0] is not a:  # holding `a` keeps its id from naming another array
            if len(views) > 16:
                views.clear()
            hit = views[id(a)] = (a, a.numpy())
        return hit[1]

    def pinned_ints(self, count: int):
        """A pinned host int32 buffer of at least `count` entries and its numpy view (GPU reads land there)."""
        size = max(16, count)
        host = self._cache.get("pinned_ints")
        if host is None or host.shape[0] < size:
            host = self._cache["pinned_ints"] = wp.empty(size, dtype=wp.int32, device="cpu", pinned=True)
            self._cache["pinned_ints_np"] = host.numpy()
        return host, self._cache["pinned_ints_np"]


_SORT, _SCAN, _ZERO = object(), object(), object()  # op kinds of a LaunchSequence (launch keys are anything else)


class LaunchSequence:
    """Launches whose sizes and arguments are all known before any of them runs, issued together: eagerly (through
    the workspace's LaunchCache) on the CPU, or as one CUDA graph when the same sequence came before (GraphCache).
    Ends with host reads of a few device ints (`read_ints`), made with one synchronisation by `run`.

    immediate=True issues each op as it is added (no graph), for stage timing (tile_binning.stage_hook)."""

    def __init__(self, ws: Workspace, immediate: bool = False):
        self.ws = ws
        self.immediate = immediate
        self.ops: list = []
        self.reads: list = []
        self._read_size = 0
        self._checks: list = []

    def _add(self, op) -> None:
        if self.immediate:
            self._issue_op(op)
        else:
            self.ops.append(op)

    def launch(self, key, kernel, dim: int, args, block_dim: int = 0) -> None:
        if dim > 0:
            self._add((key, kernel, dim, [a.__ctype__() if isinstance(a, _ARRAY) else a for a in args], block_dim))

    def sort_pairs(self, keys: wp.array, values: wp.array, count: int, begin_bit: int = 0, end_bit=None) -> None:
        self._add((_SORT, keys, values, count, begin_bit, end_bit))

    def scan(self, src: wp.array, dst: wp.array) -> None:
        """Inclusive prefix sum."""
        self._add((_SCAN, src, dst))

    def zero(self, a: wp.array) -> None:
        self._add((_ZERO, a))

    def read_ints(self, a: wp.array, index: int, count: int = 1) -> int:
        """Asks for a[index : index + count] on the host; returns where they start in `run`'s list."""
        self.reads.append((a, index, count, self._read_size))
        self._read_size += count
        return self._read_size - count

    def has_checks(self) -> bool:
        return bool(self._checks)

    def on_values(self, check) -> None:
        """check(values) runs on the values read, before `run` returns them (e.g. raises for flagged input)."""
        self._checks.append(check)

    def run(self) -> list:
        """Issues the sequence and returns the ints asked for (one host sync when there are any)."""
        return self._run(None)

    def run_unwaited(self, host) -> None:
        """Issues the sequence with its reads copied into the int buffer `host` (pinned, on a GPU), without waiting
        for them: the caller records an event after and reads `host` once it has passed (on the CPU they are there
        on return). Sequences with checks cannot: the checks read the values."""
        if self._checks:
            raise ValueError("LaunchSequence.run_unwaited: a sequence with checks needs its values now")
        if self.ws.device.is_cpu:
            values = self._run(None)
            host.numpy()[: len(values)] = values
            return
        self._run(host)

    def run_deferred(self):
        """Issues the sequence and its reads without waiting for them; returns collect(), which waits for the reads
        only (not for work queued after them: the GPU keeps busy meanwhile), runs the checks and returns the
        values as `run` would."""
        ws = self.ws
        if ws.device.is_cpu:
            values = self._host_values()
            return lambda: self._checked(values)
        host_np = self._issue_on_gpu(None)
        event = ws.memo("read_event", lambda: wp.Event(ws.device))
        ws.device.stream.record_event(event)

        def collect() -> list:
            wp.synchronize_event(event)
            return self._checked(host_np[: self._read_size].tolist())
        return collect

    def _run(self, host) -> list:
        ws = self.ws
        if ws.device.is_cpu:
            return self._checked(self._host_values())
        host_np = self._issue_on_gpu(host)
        if host is not None:
            return []
        if self.reads:
            wp.synchronize_stream(ws.device.stream)
        return self._checked(host_np[: self._read_size].tolist())  # Python ints

    def _host_values(self) -> list:
        """The CPU: issues the sequence and returns the values read (zero-copy views of host memory)."""
        self._issue()
        values = []
        for a, index, count, _ in self.reads:
            values.extend(self.ws.host_view(a)[index: index + count].tolist())
        return values

    def _issue_on_gpu(self, host):
        """Issues the sequence (as a CUDA graph when it came before) with its reads copied into `host`, or (None)
        into the workspace's pinned ints, whose numpy view it returns."""
        ws = self.ws
        self._host, host_np = ws.pinned_ints(self._read_size) if host is None else (host, None)
        if not self.immediate and ws.graphs.enabled():
            ws.graphs.run(*self._key(), self._issue, self._largest_sort)
        else:
            self._issue()
        return host_np

    def _checked(self, values: list) -> list:
        for check in self._checks:
            check(values)
        return values

    def _issue(self) -> None:
        for op in self.ops:
            self._issue_op(op)
        if not self.ws.device.is_cpu:
            for a, index, count, slot in self.reads:
                wp.copy(self._host, a, dest_offset=slot, src_offset=index, count=count)

    def _issue_op(self, op) -> None:
        kind = op[0]
        if kind is _SORT:
            wp.utils.radix_sort_pairs(op[1], op[2], op[3], begin_bit=op[4], end_bit=op[5])
        elif kind is _SCAN:
            wp.utils.array_scan(op[1], op[2], inclusive=True)
        elif kind is _ZERO:
            op[1].zero_()
        else:
            self.ws.launches.launch_params(op[0], op[1], op[2], op[3], op[4])

    def _largest_sort(self) -> int:
        return max([op[3] for op in self.ops if op[0] is _SORT], default=0)

    def _key(self):
        """(key, referents): the key is everything the issued work depends on except memory contents, with arrays
        and descriptors by identity (a view or descriptor object stands for one address, shape and strides: the
        workspace and the descriptor memo hand out the same object for the same memory) and scalars by value. The
        referents keep those objects alive as long as the key is stored, so no other object can take their ids."""
        parts = []
        for op in self.ops:
            kind = op[0]
            if kind is _SORT or kind is _SCAN or kind is _ZERO:
                parts.append((id(kind),) + tuple([a if type(a) in _BY_VALUE else id(a) for a in op[1:]]))
            else:
                parts.append((kind, id(op[1]), op[2], op[4],
                              tuple([a if type(a) in _BY_VALUE else id(a) for a in op[3]])))
        for a, index, count, slot in self.reads:
            parts.append((id(a), index, count, slot))
        parts.append(id(self._host))
        # the ops and reads hold every object named by id (LaunchCache copies a launch's parameters, so these lists
        # never change once the sequence is built)
        return tuple(parts), [self.ops, self.reads, self._host]


_BY_VALUE = (int, float, bool)  # launch arguments keyed by value; the rest (arrays, descriptors, structs) by identity
