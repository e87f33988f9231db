"""Tile binning: which tiles each projected Gaussian touches, (tile, depth) sort keys, per-tile ranges.

A Gaussian reaches a tile only if some pixel centre in that tile can receive alpha >= alpha_min from it
(1/255 by default), so the footprint is the exact bounding box of the ellipse q <= 2 ln(o / alpha_min)
(about 3.3 sigma at o = 0.99 and alpha_min = 1/255, less for fainter Gaussians): no contribution the
blending rule would keep is ever truncated, and the result does not depend on the tile size.
`max_sigmas` > 0 truncates the footprint further (a speed knob); so does a larger alpha_min.
"""
import warp as wp


@wp.kernel
def tile_footprints(
    means2d: wp.array(dtype=wp.vec2),
    cov2d: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    valid: wp.array(dtype=wp.int32),
    width: int,
    height: int,
    tile_size: int,
    max_sigmas: float,
    alpha_min: float,  # the blending's alpha threshold
    rects: wp.array(dtype=wp.vec4i),  # tile x0, y0, x1, y1 (inclusive)
    counts: wp.array(dtype=wp.int32),
    q_cut: wp.array(dtype=float),  # blending skips a pixel beyond this Mahalanobis distance without an exp()
):
    i = wp.tid()
    counts[i] = 0
    q_cut[i] = 0.0
    rects[i] = wp.vec4i(0, 0, -1, -1)
    o = opacities[i]
    if valid[i] == 0 or o < alpha_min:
        return
    q_alpha = 2.0 * wp.log(o / alpha_min)  # alpha = o exp(-q/2) >= alpha_min  <=>  q <= q_alpha
    q_max = q_alpha
    if max_sigmas > 0.0:
        q_max = wp.min(q_max, max_sigmas * max_sigmas)
    # A hair generous: the exact alpha >= alpha_min test still runs inside, so this only saves work.
    q_cut[i] = q_max * 1.0001 + 1.0e-4
    if max_sigmas > 0.0 and q_max < q_alpha:
        q_cut[i] = q_max  # a hard truncation at max_sigmas: pixels beyond it are skipped
    cv = cov2d[i]
    # Slightly generous so that float rounding never drops a pixel the blending would keep.
    ex = wp.sqrt(q_max * cv[0]) * 1.0001 + 0.01
    ey = wp.sqrt(q_max * cv[2]) * 1.0001 + 0.01
    m = means2d[i]
    # Pixel centres sit at +0.5; clamp in float before converting so huge footprints cannot overflow int.
    x_lo = wp.clamp(m[0] - ex - 0.5, -1.0, float(width) + 1.0)
    x_hi = wp.clamp(m[0] + ex - 0.5, -1.0, float(width) + 1.0)
    y_lo = wp.clamp(m[1] - ey - 0.5, -1.0, float(height) + 1.0)
    y_hi = wp.clamp(m[1] + ey - 0.5, -1.0, float(height) + 1.0)
    px0 = wp.max(int(wp.ceil(x_lo)), 0)
    px1 = wp.min(int(wp.floor(x_hi)), width - 1)
    py0 = wp.max(int(wp.ceil(y_lo)), 0)
    py1 = wp.min(int(wp.floor(y_hi)), height - 1)
    if px0 > px1 or py0 > py1:
        return
    tx0 = px0 / tile_size
    tx1 = px1 / tile_size
    ty0 = py0 / tile_size
    ty1 = py1 / tile_size
    rects[i] = wp.vec4i(tx0, ty0, tx1, ty1)
    counts[i] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)


# Sorting: primitives are first sorted by depth (N 32-bit keys), then their tile keys are emitted in that order and
# stable-sorted by tile alone (tile-index bits only). The result is the (tile, depth) order a single sort of
# 64-bit (tile << 32 | depth) keys gives, ties included (both are stable by primitive index), for a fraction of
# the passes over the tile pairs, which outnumber the primitives 10-30x.


@wp.kernel
def depth_sort_keys(
    depth_bits: wp.array(dtype=wp.int32),  # float32 camera depth reinterpreted (positive: order-preserving)
    keys: wp.array(dtype=wp.int32),  # [2N] (the sort's room)
    order: wp.array(dtype=wp.int32),  # [2N]
):
    i = wp.tid()
    keys[i] = depth_bits[i]
    order[i] = i


@wp.kernel
def counts_in_order(order: wp.array(dtype=wp.int32), counts: wp.array(dtype=wp.int32),
                    ordered_counts: wp.array(dtype=wp.int32)):
    j = wp.tid()
    ordered_counts[j] = counts[order[j]]


@wp.kernel
def emit_tile_keys(
    rects: wp.array(dtype=wp.vec4i),
    order: wp.array(dtype=wp.int32),  # primitives by depth
    offsets: wp.array(dtype=wp.int32),  # inclusive prefix sum of the counts in that order
    counts: wp.array(dtype=wp.int32),
    tiles_x: int,
    keys: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.int32),
):
    """Each primitive's tile keys, one thread per primitive (the CPU's version: few threads, no search)."""
    j = wp.tid()
    i = order[j]
    n = counts[i]
    if n == 0:
        return
    r = rects[i]
    k = offsets[j] - n
    for ty in range(r[1], r[3] + 1):
        for tx in range(r[0], r[2] + 1):
            keys[k] = ty * tiles_x + tx
            values[k] = i
            k += 1


@wp.func
def pair_slot_within(offsets: wp.array(dtype=wp.int32), first: int, last: int, k: int) -> int:
    """The slot whose key range holds pair k: the first whose inclusive prefix sum `offsets` exceeds k, searched
    in [first, last], which the caller knows holds it."""
    lo = first
    hi = last
    while lo < hi:
        mid = (lo + hi) / 2
        if offsets[mid] > k:
            hi = mid
        else:
            lo = mid + 1
    return lo


@wp.func
def pair_slot(offsets: wp.array(dtype=wp.int32), num_primitives: int, k: int) -> int:
    """pair_slot_within over every slot."""
    return pair_slot_within(offsets, 0, num_primitives - 1, k)


@wp.func
def pair_tile(r: wp.vec4i, local: int, tiles_x: int) -> int:
    """The tile index of the local-th tile (row by row) of the tile rectangle r = (x0, y0, x1, y1)."""
    width = r[2] - r[0] + 1
    return (r[1] + local / width) * tiles_x + r[0] + local % width


@wp.kernel
def emit_tile_keys_per_pair(
    rects: wp.array(dtype=wp.vec4i),
    order: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    tiles_x: int,
    num_primitives: int,
    keys: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.int32),
):
    """The same keys as `emit_tile_keys`, one thread per (primitive, tile) pair instead of per primitive: a large
    primitive's thousands of tiles no longer serialise on one GPU thread, and writes are coalesced. Each thread
    finds its primitive by binary search in the prefix sum (worth it on GPUs; the CPU keeps the loop)."""
    k = wp.tid()
    slot = pair_slot(offsets, num_primitives, k)
    i = order[slot]
    keys[k] = pair_tile(rects[i], k - (offsets[slot] - counts[i]), tiles_x)
    values[k] = i


# The per-pair search over all N slots costs ~log2(N) dependent loads a pair (20 at 1M Gaussians, for 5-10 million
# pairs). A coarse table first finds the slot of every PAIR_TABLE_STRIDE-th pair; each pair then searches only
# between its two table entries, a window the 32 threads of a warp share (a few slots at typical tile counts).
PAIR_TABLE_STRIDE = 32


def pair_table_length(total: int) -> int:
    """Entries of the coarse table for `total` pairs: one per stride, plus the one after the last pair's."""
    return (total - 1) // PAIR_TABLE_STRIDE + 2


@wp.kernel
def pair_slot_table(
    offsets: wp.array(dtype=wp.int32),
    num_primitives: int,
    total: int,
    table: wp.array(dtype=wp.int32),  # [pair_table_length(total)]
):
    """table[b]: the slot of pair b * PAIR_TABLE_STRIDE (of the last pair past the end), so pair k's slot lies in
    [table[k / stride], table[k / stride + 1]]."""
    b = wp.tid()
    table[b] = pair_slot(offsets, num_primitives, wp.min(b * PAIR_TABLE_STRIDE, total - 1))


@wp.func
def emit_pair_by_table(k: int, rects: wp.array(dtype=wp.vec4i), order: wp.array(dtype=wp.int32),
                       offsets: wp.array(dtype=wp.int32), counts: wp.array(dtype=wp.int32),
                       table: wp.array(dtype=wp.int32), tiles_x: int, keys: wp.array(dtype=wp.int32),
                       values: wp.array(dtype=wp.int32)):
    """Pair k's tile key and primitive, its slot searched between the coarse table's two entries around it."""
    b = k / PAIR_TABLE_STRIDE
    slot = pair_slot_within(offsets, table[b], table[b + 1], k)
    i = order[slot]
    keys[k] = pair_tile(rects[i], k - (offsets[slot] - counts[i]), tiles_x)
    values[k] = i


@wp.kernel
def emit_tile_keys_by_table(
    rects: wp.array(dtype=wp.vec4i),
    order: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    table: wp.array(dtype=wp.int32),  # pair_slot_table's
    tiles_x: int,
    keys: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.int32),
):
    """`emit_tile_keys_per_pair` with each pair's search narrowed by the coarse table."""
    emit_pair_by_table(wp.tid(), rects, order, offsets, counts, table, tiles_x, keys, values)


@wp.kernel
def tile_ranges(
    keys: wp.array(dtype=wp.int32),  # sorted tile indices
    count: int,
    tile_start: wp.array(dtype=wp.int32),  # [num_tiles], zeroed beforehand
    tile_end: wp.array(dtype=wp.int32),  # [num_tiles], zeroed beforehand
):
    k = wp.tid()
    tile = keys[k]
    if k == 0:
        tile_start[tile] = 0
    elif keys[k - 1] != tile:
        tile_start[tile] = k
    if k == count - 1:
        tile_end[tile] = count
    elif keys[k + 1] != tile:
        tile_end[tile] = k + 1


# --- Kernels of the lean host path (warpgs/render/fast_pipeline.py) ---------------------------------------------
# Same keys and order as above; these avoid host-side work: float depth keys need no reinterpreting view, and the
# tile ranges are written for every tile (no zero-fill first).


@wp.kernel
def depth_sort_init(
    depths: wp.array(dtype=float),  # positive camera depths: float radix keys order them
    keys: wp.array(dtype=float),  # [2N] (the sort's room)
    order: wp.array(dtype=wp.int32),  # [2N]
):
    i = wp.tid()
    keys[i] = depths[i]
    order[i] = i


@wp.func
def write_tile_ranges(k: int, keys: wp.array(dtype=wp.int32), count: int, num_tiles: int,
                      tile_start: wp.array(dtype=wp.int32), tile_end: wp.array(dtype=wp.int32)):
    """Entry k of the `count` sorted keys is in `tile`, entry k-1 in `prev` (-1 for k = 0): k starts `tile` and ends
    `prev`; the empty tiles in between start and end at k; the last entry ends its tile and empties the tiles after
    it. So every tile is written exactly once."""
    tile = keys[k]
    prev = int(-1)
    if k > 0:
        prev = keys[k - 1]
    if tile != prev:
        for t in range(prev + 1, tile + 1):
            tile_start[t] = k
        for t in range(prev + 1, tile):
            tile_end[t] = k
        if prev >= 0:
            tile_end[prev] = k
    if k == count - 1:
        tile_end[tile] = count
        for t in range(tile + 1, num_tiles):
            tile_start[t] = count
            tile_end[t] = count


@wp.kernel
def tile_ranges_dense(
    keys: wp.array(dtype=wp.int32),  # sorted tile indices
    count: int,
    num_tiles: int,
    tile_start: wp.array(dtype=wp.int32),  # [num_tiles], every entry written
    tile_end: wp.array(dtype=wp.int32),
):
    write_tile_ranges(wp.tid(), keys, count, num_tiles, tile_start, tile_end)


# --- Bounded binning: room for the tile pairs sized before their count is known ---------------------------------
# A GPU render normally reads its tile-pair count back to size the pair sort, a host sync in every call. These
# kernels take a room `capacity` fixed beforehand (from earlier calls, render/pair_room.py) and read the count from
# the prefix sum on the device: slots past the count get a sentinel key (the tile count, after every real tile), and
# pairs past the room are dropped, which the caller learns from `pair_overflow` and must treat as a failed render.


@wp.func
def bounded_total(offsets: wp.array(dtype=wp.int32), num_primitives: int, capacity: int) -> int:
    """The pairs that fit: the inclusive prefix sum's last entry, clamped to the room."""
    return wp.min(offsets[num_primitives - 1], capacity)


@wp.kernel
def pair_slot_table_bounded(
    offsets: wp.array(dtype=wp.int32),
    num_primitives: int,
    capacity: int,
    table: wp.array(dtype=wp.int32),  # [pair_table_length(capacity)]
):
    """`pair_slot_table` over the pairs that fit the room (all zeros when there are none)."""
    b = wp.tid()
    total = bounded_total(offsets, num_primitives, capacity)
    if total == 0:
        table[b] = 0
        return
    table[b] = pair_slot(offsets, num_primitives, wp.min(b * PAIR_TABLE_STRIDE, total - 1))


@wp.kernel
def emit_tile_keys_bounded(
    rects: wp.array(dtype=wp.vec4i),
    order: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    table: wp.array(dtype=wp.int32),  # pair_slot_table_bounded's
    num_primitives: int,
    capacity: int,
    tiles_x: int,
    num_tiles: int,
    keys: wp.array(dtype=wp.int32),  # [capacity] at least
    values: wp.array(dtype=wp.int32),
):
    """`emit_tile_keys_by_table` over `capacity` slots: a slot past the pairs gets the sentinel key num_tiles."""
    k = wp.tid()
    if k >= bounded_total(offsets, num_primitives, capacity):
        keys[k] = num_tiles
        values[k] = 0
        return
    emit_pair_by_table(k, rects, order, offsets, counts, table, tiles_x, keys, values)


@wp.kernel
def tile_ranges_bounded(
    keys: wp.array(dtype=wp.int32),  # sorted: the pairs that fit, then sentinels
    offsets: wp.array(dtype=wp.int32),
    num_primitives: int,
    capacity: int,
    num_tiles: int,
    tile_start: wp.array(dtype=wp.int32),  # [num_tiles], every entry written
    tile_end: wp.array(dtype=wp.int32),
):
    """`tile_ranges_dense` with the pair count read on the device; with no pairs, every tile is empty."""
    k = wp.tid()
    count = bounded_total(offsets, num_primitives, capacity)
    if count == 0:
        if k == 0:
            for t in range(num_tiles):
                tile_start[t] = 0
                tile_end[t] = 0
        return
    if k >= count:
        return
    write_tile_ranges(k, keys, count, num_tiles, tile_start, tile_end)


@wp.kernel
def pair_overflow(offsets: wp.array(dtype=wp.int32), num_primitives: int, capacity: int,
                  overflowed: wp.array(dtype=wp.int32)):
    """overflowed[0] = 1 when the pairs outnumber the room (the render dropped some), else 0."""
    overflowed[0] = wp.where(offsets[num_primitives - 1] > capacity, 1, 0)
