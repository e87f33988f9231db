"""CUDA graphs of a workspace's launch sequences (workspace.LaunchSequence): when to capture a sequence, when to
replay it, and the capture stream's radix-sort scratch the captured sorts use. Torch-free."""
from __future__ import annotations

import os
import warnings
from collections import OrderedDict

import warp as wp

# CUDA graphs of fixed launch sequences (LaunchSequence.run). WARPGS_RASTER_GRAPHS=0 turns them off (benchmarks
# compare both in one process by setting `GRAPHS_ENABLED`).
GRAPHS_ENABLED = os.environ.get("WARPGS_RASTER_GRAPHS", "1") != "0"
# Graphs per workspace: a renderer alternating between a few buffer sets, and the pair sorts of a few padded pair
# counts (tile_binning.padded_capacity: a moving camera's), keep them all (a graph of a dozen launches is small).
_GRAPHS_KEPT = 16
_KEYS_SEEN = 32  # keys remembered once; a key seen a second time is captured


class GraphCache:
    """CUDA graphs of launch sequences, keyed by everything a graph bakes in (array addresses and shapes, launch
    sizes, scalar arguments). A sequence is captured the second time its key comes (a key seen once costs
    nothing), and replayed while its key repeats. Capture runs on a private stream (CUDA cannot capture the legacy
    default stream, which is torch's default); the graph is launched on the caller's stream.

    The private stream must not block with the legacy stream: while a blocking stream captures, any other thread's
    work on the legacy stream (torch's default) fails. `stream_factory` makes it; the torch bridge sets one that
    makes a non-blocking stream (Warp's own streams are blocking)."""

    def __init__(self, device):
        self.device = device
        self.stream_factory = lambda: wp.Stream(self.device)
        self._graphs: "OrderedDict[tuple, tuple]" = OrderedDict()  # key -> (graph, referents)
        self._seen: "OrderedDict[tuple, list]" = OrderedDict()  # key -> referents
        self._stream = None
        self.broken = False  # set when a capture failed: this workspace launches eagerly from then on
        self.captures = 0  # counters, for tests and benchmarks
        self.replays = 0
        self.sort_room = 0  # items the capture stream's radix-sort scratch holds (see reserve_sorts)

    def enabled(self) -> bool:
        return GRAPHS_ENABLED and self.device.is_cuda and not self.broken

    def run(self, key: tuple, referents: list, issue, largest_sort=lambda: 0) -> None:
        """Runs `issue()` (launches only: no allocation, no host sync) as a graph when `key` came before, else
        eagerly. `referents`: the objects whose ids the key holds, kept alive with it. largest_sort(): the most
        items one radix sort of `issue` sorts (0: none), asked only when capturing. Must be called with the
        caller's stream current on the device."""
        stream = self.device.stream
        hit = self._graphs.get(key)
        if hit is not None:
            self._graphs.move_to_end(key)
            wp.capture_launch(hit[0], stream=stream)
            self.replays += 1
            return
        if key not in self._seen:
            self._seen[key] = referents
            if len(self._seen) > _KEYS_SEEN:
                self._seen.popitem(last=False)
            issue()
            return
        graph = self._capture(issue, largest_sort)
        if graph is None:
            issue()
            return
        self._seen.pop(key, None)
        self._graphs[key] = (graph, referents)
        if len(self._graphs) > _GRAPHS_KEPT:
            self._graphs.popitem(last=False)
        wp.capture_launch(graph, stream=stream)
        self.captures += 1

    def reserve_sorts(self, largest: int) -> None:
        """Warp keeps one radix-sort scratch buffer per stream and replaces it, freeing the old one, when a sort needs
        more: a graph captured before that would sort in freed memory when replayed. So before capturing sorts of up
        to `largest` items, the capture stream's scratch is made to hold twice the most asked so far (a sort outside
        any capture, full 32-bit keys: the most passes), and the graphs captured before it grew are dropped."""
        room = sort_room_for(self.sort_room, largest)
        if room is None:
            return
        self._graphs.clear()  # their sorts read the scratch this replaces
        self._grow_sort_scratch(room)
        self.sort_room = room

    def _capture_stream(self):
        if self._stream is None:
            self._stream = self.stream_factory()
        return self._stream

    def _grow_sort_scratch(self, room: int) -> None:
        stream = self._capture_stream()
        with wp.ScopedStream(stream, sync_enter=False):  # allocated, sorted and synchronised on that stream
            keys = wp.empty(2 * room, dtype=wp.int32, device=self.device)
            values = wp.empty(2 * room, dtype=wp.int32, device=self.device)
            wp.utils.radix_sort_pairs(keys, values, room)  # the contents do not matter, the scratch's size does
            wp.synchronize_stream(stream)  # before the arrays go (rare: the scratch at least doubles)
            del keys, values

    def _capture(self, issue, largest_sort):
        try:
            self.reserve_sorts(largest_sort())
            stream = self._capture_stream()
            with wp.ScopedStream(stream, sync_enter=False):
                with wp.ScopedCapture(device=self.device, stream=stream) as capture:
                    issue()
            return capture.graph
        except Exception as exc:  # never fail a render for want of a graph: launch eagerly from now on
            self.broken = True
            warnings.warn(f"warpgs: CUDA graph capture failed ({exc}); rendering without graphs", RuntimeWarning)
            return None


def sort_room_for(room: int, largest: int):
    """The radix-sort scratch (in items) to reserve before capturing sorts of up to `largest` items when `room` is
    reserved already: None when it suffices, else twice `largest` (so that it grows rarely)."""
    return None if largest <= room else 2 * largest
