"""Tile-key emission: the GPU's one-thread-per-pair kernel writes exactly what the per-primitive loop writes."""
import numpy as np
import pytest
import warp as wp

from warpgs.kernels import binning


def emit(kernel, rects, counts, depth_bits, tiles_x):
    offsets = np.cumsum(counts).astype(np.int32)
    total = int(offsets[-1])
    arr = lambda a, dt: wp.array(a, dtype=dt, device="cpu")  # noqa: E731
    keys = wp.zeros(total, dtype=wp.int64, device="cpu")
    values = wp.zeros(total, dtype=wp.int32, device="cpu")
    inputs = [arr(rects, wp.vec4i), arr(offsets, wp.int32), arr(counts, wp.int32), arr(depth_bits, wp.int32), tiles_x]
    if kernel is binning.emit_tile_keys:
        wp.launch(kernel, dim=len(counts), inputs=inputs, outputs=[keys, values], device="cpu")
    else:
        wp.launch(kernel, dim=total, inputs=inputs + [len(counts)], outputs=[keys, values], device="cpu")
    return keys.numpy(), values.numpy()


@pytest.mark.parametrize("seed", [0, 1])
def test_per_pair_emission_matches_the_per_primitive_loop(seed):
    rng = np.random.default_rng(seed)
    n, tiles_x, tiles_y = 300, 13, 9
    x0, y0 = rng.integers(0, tiles_x, n), rng.integers(0, tiles_y, n)
    x1 = np.minimum(x0 + rng.integers(0, 6, n), tiles_x - 1)
    y1 = np.minimum(y0 + rng.integers(0, 6, n), tiles_y - 1)
    culled = rng.random(n) < 0.3  # culled primitives touch no tile (count 0), as the footprint kernel leaves them
    rects = np.stack([x0, y0, x1, y1], 1).astype(np.int32)
    rects[culled] = (0, 0, -1, -1)
    counts = np.where(culled, 0, (x1 - x0 + 1) * (y1 - y0 + 1)).astype(np.int32)
    depth_bits = rng.random(n).astype(np.float32).view(np.int32)
    loop_keys, loop_values = emit(binning.emit_tile_keys, rects, counts, depth_bits, tiles_x)
    pair_keys, pair_values = emit(binning.emit_tile_keys_per_pair, rects, counts, depth_bits, tiles_x)
    assert len(loop_keys) == counts.sum() > 1000
    np.testing.assert_array_equal(pair_keys, loop_keys)
    np.testing.assert_array_equal(pair_values, loop_values)
