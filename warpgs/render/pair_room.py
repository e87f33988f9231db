"""Room for a GPU render's tile pairs, sized from earlier calls' counts (torch-free).

A render learns how many (tile, primitive) pairs it has only after the projection and the prefix sum; reading that
count back to size the pair sort is a host sync in every call, and in a training step it leaves the GPU idle while
the host queues the rest of the step. A render with `speculative_pairs` sorts into a room fixed beforehand instead
(kernels/binning.py's bounded kernels) and reads its count back without waiting: the next such call settles it,
by then long done, and grows the room when it was too small. A call whose pairs did not fit drops some of them,
which its overflow flag says on the device (the trainer skips that step through fused Adam's found_inf, as it does
a non-finite one).

The room is the largest count of the last WINDOW calls times HEADROOM, rounded up to one of a few sizes per
doubling, so it changes seldom (each size is another CUDA graph of the pre-blend launches). A workspace keeps one
room per primitive kind, image and tile size (`PairRooms`): counts scale with the pixels, so a run whose views change
size (train.resolution_schedule, captures of mixed sizes) starts each size with an exact count instead of overflowing,
and a surfel's footprint covers other tiles than a 3D Gaussian's.
"""
from __future__ import annotations

import math
from collections import deque
from typing import Optional

import warp as wp

HEADROOM = 1.3  # views of one scene differ in pairs; densification grows them between visits
# Renders that sort ahead of their count (sort_ahead.AheadSort) redo an overflow instead of dropping a step, and sort
# every slot of the room: less headroom (a moving camera's counts change a few percent a view).
AHEAD_HEADROOM = 1.1
# ... and sort ahead only while the room is at most this multiple of the last count: after a view with many more pairs
# (a viewer zoomed out, then in), the room keeps the largest of the last WINDOW counts, and sorting it whole would
# cost more than the count's wait it saves; such renders read their count first (and the room shrinks as it ages).
AHEAD_MAX_ROOM = 2.0
WINDOW = 64  # calls remembered
SIZES_PER_DOUBLING = 8  # room sizes are 2^(k/8): at most 9% above what the rule asks for
MIN_ROOM = 1024


def room_size(needed: float) -> int:
    """The smallest size 2^(k / SIZES_PER_DOUBLING) (k an integer) that holds `needed` pairs, at least MIN_ROOM."""
    needed = max(float(needed), MIN_ROOM)
    k = math.ceil(SIZES_PER_DOUBLING * math.log2(needed) - 1e-9)
    return int(math.ceil(2.0 ** (k / SIZES_PER_DOUBLING)))


class PairRoom:
    """The room for one image size's tile pairs and the one count read still in flight. `capacity` is 0 until a count
    has been seen (the first call then sizes exactly, with its sync). `overflows` / `speculative_calls` count the calls
    whose pairs did not fit and all calls sized from the room, for benchmarks and the trainer's report."""

    def __init__(self, headroom: float = HEADROOM):
        self.capacity = 0
        self.headroom = headroom
        self.recent: deque = deque(maxlen=WINDOW)
        self.overflows = 0
        self.speculative_calls = 0
        self._pending: Optional[tuple] = None  # (event, the host buffer's numpy view, the room that call had)
        self._event = None
        self._host = None

    def observe(self, total: int) -> None:
        """A call's exact pair count: the room follows the recent largest."""
        self.recent.append(int(total))
        self.capacity = room_size(max(self.recent) * self.headroom)

    def suits_last(self, most: float) -> bool:
        """Whether the room is sized (capacity > 0) and at most `most` times the last count it saw (or MIN_ROOM)."""
        return 0 < self.capacity <= max(most * (self.recent[-1] if self.recent else 0), MIN_ROOM)

    def settle(self) -> None:
        """Reads the last speculative call's count (waiting on its event, normally long passed) and notes an
        overflow. Call before another call may write the pinned buffer."""
        pending, self._pending = self._pending, None
        if pending is None:
            return
        event, host, capacity = pending
        if event is not None:
            wp.synchronize_event(event)
        total = int(host[0])
        if total > capacity:
            self.overflows += 1
        self.observe(total)

    def host_buffer(self, device):
        """The pinned int buffer speculative calls copy their count into (one per room: exact calls' reads use the
        workspace's own, so neither overwrites a count the other has not read)."""
        if self._host is None:
            cuda = wp.get_device(device).is_cuda
            self._host = wp.empty(16, dtype=wp.int32, device="cpu", pinned=cuda)
            self._event = wp.Event(device) if cuda else None
        return self._host

    def issued(self, stream, capacity: int) -> None:
        """The speculative call's count copy is queued on `stream` (None on the CPU, where it is written already):
        record the event settle waits on."""
        if stream is not None:
            stream.record_event(self._event)
        self._pending = (self._event, self._host.numpy(), capacity)
        self.speculative_calls += 1

    def stats(self) -> dict:
        self.settle()
        return {"capacity": self.capacity, "speculative_calls": self.speculative_calls, "overflows": self.overflows}


class PairRooms:
    """A workspace's rooms, one per (primitive kind, width, height, tile size), and one more per such key for the
    renders that sort ahead of their count (sort_ahead.AheadSort)."""

    def __init__(self):
        self.rooms: dict = {}

    def room(self, key: tuple, headroom: float = HEADROOM) -> PairRoom:
        room = self.rooms.get(key)
        if room is None:
            room = self.rooms[key] = PairRoom(headroom)
        return room

    def stats(self) -> dict:
        """Speculative calls and overflows summed over the rooms (each room's count read settled first)."""
        total = {"speculative_calls": 0, "overflows": 0}
        for room in self.rooms.values():
            stats = room.stats()
            for k in total:
                total[k] += stats[k]
        return total
