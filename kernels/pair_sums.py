"""Fixed-order gradient sums for the deterministic GPU blend adjoint (raster option `deterministic`).

The default adjoints add each tile's (or warp's) per-primitive sum to the primitive's gradient with a float atomic,
so on a GPU the order of those additions, and the last bits of the result, change from run to run. In deterministic
mode each summing group of a tile (a warp, or a block for `backward_kernel`; `parts` groups per tile) writes its sum
for sorted pair k to its own slot k * parts + part (`pair_part_index`), and `sum_pair_parts` then adds a primitive's
slots in one fixed order: its tiles in the order binning emitted them (row by row over its tile rectangle), and
within a tile its parts in order.

`pair_ranges` and `pair_positions` recover that order after the (tile, depth) sort: the emit step wrote primitive
i's pairs at [offsets - counts, offsets) of its depth rank, tile by tile (binning.pair_tile), so the slot a sorted
pair came from follows from its tile and the primitive's tile rectangle.
"""
import warp as wp


@wp.func
def pair_part_index(k: int, tid: int, tile_size: int, group: int) -> int:
    """The slot of sorted pair k's sum from the summing group (`group` consecutive threads of a tile) that launch
    thread tid belongs to (launches start at a tile boundary: tid % tile_size² is the thread's place in its tile)."""
    per_tile = tile_size * tile_size
    return k * (per_tile / group) + (tid % per_tile) / group


@wp.kernel
def pair_ranges(
    order: wp.array(dtype=wp.int32),  # primitives by depth
    offsets: wp.array(dtype=wp.int32),  # inclusive prefix sum of the tile counts in that order
    counts: wp.array(dtype=wp.int32),
    ranges: wp.array(dtype=wp.vec2i),  # [N]: (first emitted pair, number of pairs) per primitive
):
    j = wp.tid()
    i = order[j]
    ranges[i] = wp.vec2i(offsets[j] - counts[i], counts[i])


@wp.kernel
def pair_positions(
    sorted_ids: wp.array(dtype=wp.int32),  # primitive of each sorted pair
    tile_keys: wp.array(dtype=wp.int32),  # tile of each sorted pair
    rects: wp.array(dtype=wp.vec4i),  # tile x0, y0, x1, y1 (inclusive) per primitive
    ranges: wp.array(dtype=wp.vec2i),
    tiles_x: int,
    positions: wp.array(dtype=wp.int32),  # [pairs]: emitted slot -> sorted position
):
    k = wp.tid()
    i = sorted_ids[k]
    r = rects[i]
    tile = tile_keys[k]
    local = (tile / tiles_x - r[1]) * (r[2] - r[0] + 1) + tile % tiles_x - r[0]  # inverse of binning.pair_tile
    positions[ranges[i][0] + local] = k


@wp.kernel
def sum_pair_parts(
    positions: wp.array(dtype=wp.int32),
    ranges: wp.array(dtype=wp.vec2i),
    parts: int,  # summing groups per tile
    width: int,  # floats per primitive of this gradient
    pair_values: wp.array(dtype=float),  # [pairs * parts * width]: each group's sum per sorted pair
    sums: wp.array(dtype=float),  # [N * width]: += each primitive's total
):
    t = wp.tid()
    i = t / width
    c = t % width
    r = ranges[i]
    total = float(0.0)
    for q in range(r[1]):
        first = positions[r[0] + q] * parts
        for part in range(parts):
            total += pair_values[(first + part) * width + c]
    sums[t] = sums[t] + total
