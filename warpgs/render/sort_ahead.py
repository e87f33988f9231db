"""A render's tile-pair sort queued ahead of its count (raster option pair_sort "ahead"; torch-free).

A GPU render learns its (tile, primitive) pair count only after projecting and binning; waiting for it before queuing
the pair sort and the blend leaves the GPU idle while the host does that. A render that sorts ahead queues the sort
into a room sized from earlier renders' counts (pair_room.py) and its blend first, then reads the count while the
GPU blends: if the pairs did not fit, it sorts them again in a room that holds them and blends again, so its images
and gradients are those of the exact sort either way. tile_binning.sort_into_tiles decides when a render may (the
option, the device, a room seen before and not much larger than the last count); this module holds the pending count
and the redo.
"""
from __future__ import annotations

from typing import Callable, Optional, Tuple

from warpgs.render.pair_room import PairRoom


class AheadSort:
    """A render's tile-pair sort, queued into a room before its count is read (tile_binning.sort_into_tiles'
    `ahead`). The render queues its blend, then `settle`s: the host waits for the count's copy only (the GPU is
    blending meanwhile), and a render whose pairs did not fit the room is sorted again in one that holds them."""

    def __init__(self):
        self.pending = False
        self._collect = self._at = self._room = self._redo = self._capacity = None

    def queue(self, collect: Callable[[], list], at: int, room: PairRoom, redo: Callable[[int], tuple]) -> None:
        """collect(): the sequence's values (LaunchSequence.run_deferred), the count at index `at`; redo(count): the
        sort again in a room that holds the count, (tile_start, tile_end, sorted_ids)."""
        self.pending = True
        self._collect, self._at, self._room, self._redo = collect, at, room, redo
        self._capacity = room.capacity  # what the queued sort holds
        room.speculative_calls += 1

    def settle(self) -> Tuple[int, Optional[tuple]]:
        """(the pair count, None) when the pairs fit the room, else (the count, redo()'s result: blend again with
        it). Raises for flagged input (the sequence's checks)."""
        self.pending = False
        total = int(self._collect()[self._at])
        self._room.observe(total)
        if total <= self._capacity:
            return total, None
        self._room.overflows += 1
        return total, self._redo(total)


def sort_ahead_for(overflow, deterministic: bool) -> Optional[AheadSort]:
    """An empty AheadSort for a render that is neither speculative itself (overflow None) nor deterministic (whose
    pair order is sized by its count before the blend); sort_into_tiles decides whether it sorts ahead (the option,
    the device, a room seen before)."""
    return None if overflow is not None or deterministic else AheadSort()


def settle_ahead(ahead: Optional[AheadSort], total: int, tile_start, sorted_ids, blend):
    """After a render queued its blend(tile_start, tile_end, sorted_ids): its (total, tile_start, sorted_ids), the
    count read now when it sorted ahead, and sorted and blended again when its pairs did not fit."""
    if ahead is None or not ahead.pending:
        return total, tile_start, sorted_ids
    total, redone = ahead.settle()
    if redone is not None:
        tile_start, tile_end, sorted_ids = redone
        blend(tile_start, tile_end, sorted_ids)
    return total, tile_start, sorted_ids
