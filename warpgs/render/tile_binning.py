"""Binning for the lean pipelines (fast_pipeline.py, fast_pipeline_surfels.py): each primitive's tile rectangle,
the (tile, primitive) pairs sorted by tile, then depth, then primitive index, and every tile's range of them; the
launch sequence that carries it up to the tile-pair count (workspace.LaunchSequence) and the stage hook the
benchmarks time it with. Torch-free.

Sorting takes two passes: the primitives by depth, then their tile pairs by tile index (stable). The pair count sizes
the pair sort: read back with one host sync (`sort_into_tiles`; on GPUs the sort then runs in a room of the count
padded to a sixteenth of its leading power of two, `padded_capacity`, so nearby views replay one CUDA graph), or, for
a speculative call, not read at all: the pairs go into a room sized from earlier counts (`sort_into_room`,
pair_room.py). Other GPU renders sort ahead: into a room sized from earlier such renders, queued with the blend
before their count is read; the count is then checked while the GPU blends, and a render whose pairs did not fit is
sorted again exactly and blended again (sort_ahead.py). The rooms are queued by `queue_room_sort`.
"""
from __future__ import annotations

from typing import Callable, Optional

import warp as wp

from warpgs.kernels import binning, pair_sums
from warpgs.render.defaults import current_raster_options
from warpgs.render.pair_adjoint import PairOrder
from warpgs.render.pair_room import AHEAD_HEADROOM, AHEAD_MAX_ROOM
from warpgs.render.pipeline_gaussians import Settings, _cooperative
from warpgs.render.sort_ahead import AheadSort
from warpgs.render.workspace import LaunchSequence, Workspace

Keep = Callable[[str, int, object], wp.array]  # (name, length, dtype) -> a per-call array
# Called with a stage name after each stage when set (benchmarks/profile_stages.py synchronises and times there).
stage_hook: Optional[Callable[[str], None]] = None
# Speculative binning (sort_into_tiles' `overflow`) saves a GPU's host sync; on the CPU, where reading the count
# costs nothing, it runs only when tests set this (they check it against the exact path there).
SPECULATE_ON_CPU = False


def bin_into_tiles(ws: Workspace, key: str, footprint_kernel, footprint_inputs, depths, s: Settings, per_call,
                   on_stage: Optional[Callable[[str], None]] = None, sequence: Optional[LaunchSequence] = None,
                   overflow=None, ahead: Optional[AheadSort] = None):
    """Every primitive kind's binning: its footprint kernel (inputs `footprint_inputs`, then the image and blend
    settings, writing tile rectangles, tile counts and cut-offs) and `sort_into_tiles`. Returns (counts, q_cut,
    total, tile_start, tile_end, sorted_ids); counts lives in the workspace, q_cut comes from `per_call`.
    sequence: launches already queued ahead of the binning (run with it, up to the sync)."""
    n = int(depths.shape[0])
    rects = ws.array("rects", n, wp.vec4i)
    counts = ws.array("counts", n, wp.int32)
    q_cut = per_call("q_cut", n, float)
    seq = sequence if sequence is not None else launch_sequence(ws, on_stage)
    seq.launch(key, footprint_kernel, n,
               list(footprint_inputs) + [s.width, s.height, s.tile_size, s.max_sigmas, s.alpha_min,
                                         rects, counts, q_cut])
    _stage(on_stage, key)
    return (counts, q_cut) + sort_into_tiles(ws, rects, counts, depths, s, per_call, on_stage, seq, overflow,
                                             kind=key, ahead=ahead)


def sort_into_tiles(ws: Workspace, rects, counts, depths, s: Settings, per_call,
                    on_stage: Optional[Callable[[str], None]] = None, sequence: Optional[LaunchSequence] = None,
                    overflow=None, kind: str = "footprints", ahead: Optional[AheadSort] = None):
    """(total, tile_start, tile_end, sorted_ids): the (tile, primitive) pairs sorted by tile, then depth, then
    primitive index, and every tile's [start, end) range. tile_start and sorted_ids come from `per_call`.
    sequence: launches queued ahead; everything up to the tile-pair count's read runs with them.
    overflow: a 1-element int32 array, to bin speculatively: on a GPU whose workspace has seen a count of this
    primitive kind (`kind`, its footprint kernel's key) at this image and tile size (and with no input checks
    queued), the pairs are sorted into that room (pair_room.py) without a host sync, total comes back as -1 and
    overflow[0] says whether pairs were dropped; otherwise the exact path runs and writes 0.
    ahead: an empty AheadSort (sort_ahead_for): with the pair_sort option "ahead", on a GPU whose workspace has seen
    such a render of this kind and size (and whose room is not much larger than the last count, AHEAD_MAX_ROOM), the
    pairs are sorted into that room without reading the count first; total comes back as -1 and `ahead` holds the
    pending count (AheadSort.settle)."""
    dev = ws.device
    L = ws.launches
    n = int(counts.shape[0])
    tile_start = per_call("tile_start", s.num_tiles, wp.int32)
    tile_end = ws.array("tile_end", s.num_tiles, wp.int32)
    offsets = ws.array("offsets", n, wp.int32)
    seq = sequence if sequence is not None else launch_sequence(ws, on_stage)
    depth_keys = ws.array("depth_keys", 2 * n, float)
    order = ws.array("order", 2 * n, wp.int32)
    ordered = ws.array("ordered_counts", n, wp.int32)
    seq.launch("depth_init", binning.depth_sort_init, n, [depths, depth_keys, order])
    seq.sort_pairs(depth_keys, order, n)
    seq.launch("counts_in_order", binning.counts_in_order, n, [order, counts, ordered])
    _stage(on_stage, "sort: depth sort")
    seq.scan(ordered, offsets)
    room = ws.pair_rooms.room((kind, s.width, s.height, s.tile_size)) if overflow is not None else None
    if room is not None and (dev.is_cuda or SPECULATE_ON_CPU) and room.capacity > 0 and not seq.has_checks():
        return sort_into_room(ws, room, rects, counts, s, per_call, seq, order, offsets, tile_start, tile_end,
                              overflow, on_stage)
    options = current_raster_options()
    ahead_room = None
    if ahead is not None and options.pair_sort == "ahead" and _cooperative(dev) and (dev.is_cuda or SPECULATE_ON_CPU):
        ahead_room = ws.pair_rooms.room((kind, s.width, s.height, s.tile_size, "ahead"), AHEAD_HEADROOM)
        if ahead_room.suits_last(AHEAD_MAX_ROOM):
            return sort_ahead(ws, ahead, ahead_room, rects, counts, s, per_call, seq, order, offsets, tile_start,
                              tile_end, on_stage)
    at = seq.read_ints(offsets, n - 1)
    total = seq.run()[at]  # the one host sync: sizes the pair buffers (and raises for flagged input)
    if room is not None:  # only speculative callers' counts size the room (not evaluation's or a viewer's)
        room.observe(total)
        L.launch("pair_overflow", binning.pair_overflow, 1, [offsets, n, total, overflow])
    if ahead_room is not None:  # a render of a new kind or size, or after a much larger count: the next may sort ahead
        ahead_room.observe(total)
    _stage(on_stage, "sort: prefix sum + sync")
    if total == 0:
        tile_start.zero_()
        tile_end.zero_()
        return 0, tile_start, tile_end, per_call("sorted_ids", 2, wp.int32)
    if _cooperative(dev) and options.pair_search == "table" and options.pair_sort != "exact":
        # a thread per (primitive, tile) pair (balanced across the GPU), its primitive found by a binary search
        # narrowed by a coarse table of every 32nd pair's slot; sized to a padded count, so that renders whose
        # counts differ a little (a moving camera) launch the same sequence: one CUDA graph instead of ten launches
        sorted_ids = sort_in_room(ws, padded_capacity(total), rects, order, offsets, counts, s, per_call, tile_start,
                                  tile_end, on_stage)
        _stage(on_stage, "sort: pairs (padded room)")
        return total, tile_start, tile_end, sorted_ids
    tile_bits = max(1, (s.num_tiles - 1).bit_length())
    keys = ws.array("tile_keys", 2 * total, wp.int32)
    sorted_ids = per_call("sorted_ids", 2 * total, wp.int32)  # radix sorts need 2x room
    if not _cooperative(dev):  # a loop per primitive: few threads, no search
        L.launch("emit", binning.emit_tile_keys, n, [rects, order, offsets, counts, s.tiles_x, keys, sorted_ids])
    elif options.pair_search == "table":  # pair_sort "exact": the same emission, sized to the count
        table = ws.array("pair_table", binning.pair_table_length(total), wp.int32)
        L.launch("pair_table", binning.pair_slot_table, table.shape[0], [offsets, n, total, table])
        L.launch("emit", binning.emit_tile_keys_by_table, total,
                 [rects, order, offsets, counts, table, s.tiles_x, keys, sorted_ids])
    else:  # pair_search "full": a thread per pair, each pair's search over every primitive
        L.launch("emit", binning.emit_tile_keys_per_pair, total,
                 [rects, order, offsets, counts, s.tiles_x, n, keys, sorted_ids])
    _stage(on_stage, "sort: emit keys")
    wp.utils.radix_sort_pairs(keys, sorted_ids, total, begin_bit=0, end_bit=tile_bits)
    _stage(on_stage, "sort: pair sort")
    L.launch("ranges", binning.tile_ranges_dense, total, [keys, total, s.num_tiles, tile_start, tile_end])
    _stage(on_stage, "sort: tile ranges")
    return total, tile_start, tile_end, sorted_ids


def sort_into_room(ws: Workspace, room, rects, counts, s: Settings, per_call, seq: LaunchSequence, order, offsets,
                   tile_start, tile_end, overflow, on_stage=None):
    """sort_into_tiles' speculative path: the pairs emitted, sorted and ranged within `room` (a PairRoom), all in
    the launch sequence (one CUDA graph), the count copied back unwaited (pair_room.py settles it next call)."""
    room.settle()  # before the sequence rewrites the pinned count
    capacity = room.capacity
    n = int(counts.shape[0])
    sorted_ids = queue_room_sort(ws, seq, capacity, rects, order, offsets, counts, s, per_call, tile_start, tile_end)
    seq.read_ints(offsets, n - 1)
    seq.run_unwaited(room.host_buffer(ws.device))
    room.issued(ws.device.stream if ws.device.is_cuda else None, capacity)
    ws.launches.launch("pair_overflow", binning.pair_overflow, 1, [offsets, n, capacity, overflow])
    _stage(on_stage, "sort: speculative room")
    return -1, tile_start, tile_end, sorted_ids


def sort_ahead(ws: Workspace, ahead: AheadSort, room, rects, counts, s: Settings, per_call, seq: LaunchSequence,
               order, offsets, tile_start, tile_end, on_stage=None):
    """sort_into_tiles' path ahead of the count: the count's read ends `seq` (so the host will wait for no more than
    the padded sort's sync does), the room's sort follows as a second sequence (graph) queued at once, and `ahead`
    holds the pending count with the sort to redo, in a room padded from the count, should the pairs not fit."""
    n = int(counts.shape[0])
    at = seq.read_ints(offsets, n - 1)
    collect = seq.run_deferred()
    sorted_ids = sort_in_room(ws, room.capacity, rects, order, offsets, counts, s, per_call, tile_start, tile_end,
                              on_stage)

    def redo(total: int):  # the depth order and prefix sums the first sort read are still in place
        return tile_start, tile_end, sort_in_room(ws, padded_capacity(total), rects, order, offsets, counts, s,
                                                  per_call, tile_start, tile_end, on_stage)

    ahead.queue(collect, at, room, redo)
    _stage(on_stage, "sort: ahead of the count")
    return -1, tile_start, tile_end, sorted_ids


def sort_in_room(ws: Workspace, capacity: int, rects, order, offsets, counts, s: Settings, per_call, tile_start,
                 tile_end, on_stage=None):
    """`queue_room_sort` as a launch sequence of its own (one CUDA graph once it repeats), issued at once (it reads
    nothing back: no sync). Returns sorted_ids."""
    pairs = launch_sequence(ws, on_stage)
    sorted_ids = queue_room_sort(ws, pairs, capacity, rects, order, offsets, counts, s, per_call, tile_start, tile_end)
    pairs.run()
    return sorted_ids


def queue_room_sort(ws: Workspace, seq: LaunchSequence, capacity: int, rects, order, offsets, counts, s: Settings,
                    per_call, tile_start, tile_end):
    """Queues on `seq` the pairs' emission, sort and tile ranges within `capacity` slots, the pair count read on the
    device from `offsets` (the pairs past the room are dropped; the slots past the pairs get the sentinel key
    num_tiles and sort last). Returns sorted_ids (from `per_call`); the first min(count, capacity) are the pairs'."""
    n = int(counts.shape[0])
    keys = ws.array("tile_keys", 2 * capacity, wp.int32)
    sorted_ids = per_call("sorted_ids", 2 * capacity, wp.int32)  # radix sorts need 2x room
    table = ws.array("pair_table", binning.pair_table_length(capacity), wp.int32)
    seq.launch("pair_table_bounded", binning.pair_slot_table_bounded, table.shape[0], [offsets, n, capacity, table])
    seq.launch("emit_bounded", binning.emit_tile_keys_bounded, capacity,
               [rects, order, offsets, counts, table, n, capacity, s.tiles_x, s.num_tiles, keys, sorted_ids])
    seq.sort_pairs(keys, sorted_ids, capacity, 0, max(1, s.num_tiles.bit_length()))  # the sentinel num_tiles too
    seq.launch("ranges_bounded", binning.tile_ranges_bounded, capacity,
               [keys, offsets, n, capacity, s.num_tiles, tile_start, tile_end])
    return sorted_ids


def padded_capacity(total: int) -> int:
    """total rounded up to a multiple of 1/16 of its leading power of two (at most 6.25% more slots to sort)."""
    granule = 1 << max(total.bit_length() - 5, 0)
    return -(-total // granule) * granule


def pair_order(ws: Workspace, s: Settings, keep: Optional[Keep], n: int, total: int,
               sorted_ids) -> Optional[PairOrder]:
    """For the deterministic GPU adjoint (pair_adjoint.py): where each pair emitted by `sort_into_tiles` ended up
    after the sort, and each primitive's run of emitted pairs, in `keep` (run right after the sort: it reads the
    sort's workspace arrays). None where nothing needs it: no backward follows (keep None), no pairs, or the CPU's
    per-thread kernels, which are deterministic already."""
    if keep is None or total == 0 or not _cooperative(ws.device):
        return None
    ranges = keep("pair_ranges", n, wp.vec2i)
    positions = keep("pair_positions", total, wp.int32)
    L = ws.launches
    L.launch("pair_ranges", pair_sums.pair_ranges, n,
             [ws.array("order", 2 * n, wp.int32), ws.array("offsets", n, wp.int32), ws.array("counts", n, wp.int32),
              ranges])
    L.launch("pair_positions", pair_sums.pair_positions, total,
             [sorted_ids, ws.array("tile_keys", 2 * total, wp.int32), ws.array("rects", n, wp.vec4i), ranges,
              s.tiles_x, positions])
    return PairOrder(total=total, positions=positions, ranges=ranges)


def launch_sequence(ws: Workspace, on_stage: Optional[Callable[[str], None]] = None) -> LaunchSequence:
    """The launches up to the tile-pair sync; issued one by one (no graph) while stages are being timed."""
    return ws.sequence(immediate=(on_stage or stage_hook) is not None)


def _stage(on_stage, name: str) -> None:
    hook = on_stage or stage_hook
    if hook is not None:
        hook(name)
