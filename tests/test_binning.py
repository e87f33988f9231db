"""Tile binning: pairs sorted by (tile, depth) with ties by primitive index, whatever kernel emits them."""
import numpy as np
import pytest
import warp as wp

from warpgs.render import pipeline_gaussians as pipeline
from warpgs.kernels import binning


def random_rects(seed, n=300, tiles_x=13, tiles_y=9):
    """Rectangles of 1-36 tiles, 30% culled (count 0, as the footprint kernels leave them), depths with ties."""
    rng = np.random.default_rng(seed)
    x0, y0 = rng.integers(0, tiles_x, n), rng.integers(0, tiles_y, n)
    x1 = np.minimum(x0 + rng.integers(0, 6, n), tiles_x - 1)
    y1 = np.minimum(y0 + rng.integers(0, 6, n), tiles_y - 1)
    culled = rng.random(n) < 0.3
    rects = np.stack([x0, y0, x1, y1], 1).astype(np.int32)
    rects[culled] = (0, 0, -1, -1)
    counts = np.where(culled, 0, (x1 - x0 + 1) * (y1 - y0 + 1)).astype(np.int32)
    depths = rng.choice(np.linspace(0.5, 9.0, n // 3), n).astype(np.float32)  # about 3 primitives per depth
    return rects, counts, depths


def cpu(a, dtype):
    return wp.array(a, dtype=dtype, device="cpu")


def emit(kernel, rects, counts, order, tiles_x):
    offsets = np.cumsum(counts[order]).astype(np.int32)
    total = int(offsets[-1])
    keys = wp.zeros(total, dtype=wp.int32, device="cpu")
    values = wp.zeros(total, dtype=wp.int32, device="cpu")
    wp_rects, wp_order, wp_offsets, wp_counts = (cpu(rects, wp.vec4i), cpu(order, wp.int32), cpu(offsets, wp.int32),
                                                 cpu(counts, wp.int32))
    inputs = [wp_rects, wp_order, wp_offsets, wp_counts, tiles_x]
    if kernel is binning.emit_tile_keys:
        wp.launch(kernel, dim=len(counts), inputs=inputs, outputs=[keys, values], device="cpu")
    elif kernel is binning.emit_tile_keys_by_table:
        table = wp.full(binning.pair_table_length(total), -1, dtype=wp.int32, device="cpu")
        wp.launch(binning.pair_slot_table, dim=table.shape[0], inputs=[wp_offsets, len(counts), total, table],
                  device="cpu")
        wp.launch(kernel, dim=total, inputs=[wp_rects, wp_order, wp_offsets, wp_counts, table, tiles_x],
                  outputs=[keys, values], device="cpu")
    else:
        wp.launch(kernel, dim=total, inputs=inputs + [len(counts)], outputs=[keys, values], device="cpu")
    return keys.numpy(), values.numpy()


@pytest.mark.parametrize("kernel", [binning.emit_tile_keys_per_pair, binning.emit_tile_keys_by_table])
@pytest.mark.parametrize("seed", [0, 1])
def test_per_pair_emission_matches_the_per_primitive_loop(seed, kernel):
    rects, counts, depths = random_rects(seed)
    order = np.argsort(depths, kind="stable").astype(np.int32)
    loop = emit(binning.emit_tile_keys, rects, counts, order, 13)
    pair = emit(kernel, rects, counts, order, 13)
    assert len(loop[0]) == counts.sum() > 1000
    np.testing.assert_array_equal(pair[0], loop[0])
    np.testing.assert_array_equal(pair[1], loop[1])


@pytest.mark.parametrize("case", ["one pair", "a table stride exactly", "culled runs", "one huge primitive"])
def test_table_emission_at_the_edges(case):
    """The coarse table's ends: totals at and around its stride, long runs of culled slots (count 0, so many slots
    share one prefix sum), a primitive whose pairs span many table entries."""
    stride = binning.PAIR_TABLE_STRIDE
    if case == "one pair":
        counts = np.array([0, 1, 0], np.int32)
    elif case == "a table stride exactly":
        counts = np.array([stride // 2, 0, stride // 2], np.int32)
    elif case == "culled runs":
        counts = np.zeros(500, np.int32)
        counts[[3, 250, 251, 499]] = [5, stride + 1, 2, 7]
    else:
        counts = np.array([1, 0, 13 * 9, 1], np.int32)
    n = len(counts)
    rects = np.zeros((n, 4), np.int32)
    rects[:, 2:] = -1
    for i, c in enumerate(counts):
        if c == 13 * 9:
            rects[i] = (0, 0, 12, 8)  # 13 x 9 tiles
        elif c:
            rects[i] = (0, 0, int(c) - 1, 0)  # a row of c tiles
    order = np.arange(n, dtype=np.int32)[::-1].copy()  # slots in reverse index order, as a depth sort may leave them
    loop = emit(binning.emit_tile_keys, rects, counts, order, 64)
    table = emit(binning.emit_tile_keys_by_table, rects, counts, order, 64)
    assert len(loop[0]) == counts.sum()
    np.testing.assert_array_equal(table[0], loop[0])
    np.testing.assert_array_equal(table[1], loop[1])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sorted_pairs_follow_tile_then_depth_then_index(seed):
    tiles_x, tiles_y = 13, 9
    rects, counts, depths = random_rects(seed, tiles_x=tiles_x, tiles_y=tiles_y)
    s = pipeline.Settings(width=tiles_x * 8, height=tiles_y * 8, tile_size=8)
    with wp.ScopedDevice("cpu"):
        bins = pipeline.sort_into_tiles(cpu(rects, wp.vec4i), cpu(counts, wp.int32), cpu(depths, wp.float32),
                                        None, s)
    # Reference: every (tile, primitive) pair, ordered by tile, then depth, then primitive index.
    pairs = [(ty * tiles_x + tx, depths[i], i) for i in range(len(counts)) if counts[i]
             for ty in range(rects[i, 1], rects[i, 3] + 1) for tx in range(rects[i, 0], rects[i, 2] + 1)]
    pairs.sort()
    assert bins.num_intersections == len(pairs)
    np.testing.assert_array_equal(bins.sorted_ids.numpy(), [p[2] for p in pairs])
    start, end = bins.tile_start.numpy(), bins.tile_end.numpy()
    for tile in range(tiles_x * tiles_y):
        in_tile = [k for k, p in enumerate(pairs) if p[0] == tile]
        if in_tile:
            assert (start[tile], end[tile]) == (in_tile[0], in_tile[-1] + 1)
        else:
            assert start[tile] == end[tile]


def _reference_pairs(rects, counts, depths, tiles_x):
    """Every (tile, primitive) pair, ordered by tile, then depth, then primitive index."""
    pairs = [(ty * tiles_x + tx, depths[i], i) for i in range(len(counts)) if counts[i]
             for ty in range(rects[i, 1], rects[i, 3] + 1) for tx in range(rects[i, 0], rects[i, 2] + 1)]
    pairs.sort()
    return pairs


@pytest.mark.parametrize("sort", ["per_primitive", "padded", "exact"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lean_path_sorts_match_the_reference(seed, sort, monkeypatch):
    """render/tile_binning.sort_into_tiles: same pairs, same order, and every tile's range
    written (no zero-fill beforehand: the workspace buffers start with garbage here). sort: the CPU's loop per
    primitive, or the GPU's emission (a thread per pair, run here on the CPU) into a padded room or sized exactly."""
    from warpgs.render import tile_binning
    from warpgs.render.defaults import raster_options
    from warpgs.render.workspace import Workspace

    if sort != "per_primitive":
        monkeypatch.setattr(tile_binning, "_cooperative", lambda device: True)

    tiles_x, tiles_y = 13, 9
    rects, counts, depths = random_rects(seed, tiles_x=tiles_x, tiles_y=tiles_y)
    s = pipeline.Settings(width=tiles_x * 8, height=tiles_y * 8, tile_size=8)
    ws = Workspace("cpu")
    ws.array("tile_start", s.num_tiles, wp.int32).fill_(-7)  # garbage where a kernel must write
    ws.array("tile_end", s.num_tiles, wp.int32).fill_(-7)
    pairs = _reference_pairs(rects, counts, depths, tiles_x)
    for _ in range(2):  # the second call reuses every buffer
        with raster_options(pair_sort="exact" if sort == "exact" else "padded"):
            total, start, end, ids = tile_binning.sort_into_tiles(ws, cpu(rects, wp.vec4i), cpu(counts, wp.int32),
                                                                   cpu(depths, wp.float32), s, ws.array)
        assert total == len(pairs)
        np.testing.assert_array_equal(ids.numpy()[:total], [p[2] for p in pairs])
        start, end = start.numpy(), end.numpy()
        for tile in range(tiles_x * tiles_y):
            in_tile = [k for k, p in enumerate(pairs) if p[0] == tile]
            expected = (in_tile[0], in_tile[-1] + 1) if in_tile else None
            if expected:
                assert (start[tile], end[tile]) == expected
            else:
                assert start[tile] == end[tile]


def test_padded_pair_counts_round_up_by_at_most_a_sixteenth():
    from warpgs.render.tile_binning import padded_capacity

    for total in list(range(1, 200)) + [1000, 4095, 4096, 4097, 123_457, 2_000_000, 3_999_999]:
        cap = padded_capacity(total)
        assert total <= cap <= total * (1 + 1 / 16)
        assert padded_capacity(cap) == cap  # a padded count is its own room
    assert padded_capacity(990_000) == padded_capacity(1_010_000)  # nearby views share one room (and graph)
