"""The deterministic blend adjoint (raster option / rasterize keyword `deterministic`, render/pair_adjoint.py).

On the CPU:
- the fixed-order pair sums (kernels/pair_sums.py): every emitted (primitive, tile) pair is found again after the
  (tile, depth) sort, and each primitive's sum equals a float64 sum of its pairs' parts, whatever the sort did to
  their order;
- the GPU adjoints in deterministic mode give the default path's gradients up to float32 rounding, for 3D Gaussians
  and surfels, both GPU adjoint variants, with features. These kernels run on the CPU only in cooperative mode
  (WARPGS_CPU_COOPERATIVE=1, read at import), so test_raster_gpu_kernels_on_cpu.py runs this file in that mode; in
  a plain run they are skipped, and the float64 gradient checks of the same mode run there too.
The CUDA bit-for-bit check is in test_determinism.py.
"""
import os

import numpy as np
import pytest
import torch
import warp as wp

from random_scenes import random_scene
from warpgs import rasterize, rasterize_surfels
from warpgs.kernels import binning, pair_sums
from warpgs.render.defaults import raster_options

COOPERATIVE = os.environ.get("WARPGS_CPU_COOPERATIVE") == "1"


def test_pair_sums_find_every_pair_and_add_them_in_float32_of_a_float64_sum():
    rng = np.random.default_rng(3)
    n, tiles_x, tiles_y, parts, width = 40, 9, 7, 3, 4
    x0 = rng.integers(0, tiles_x, n)
    y0 = rng.integers(0, tiles_y, n)
    x1 = np.minimum(x0 + rng.integers(0, 4, n), tiles_x - 1)
    y1 = np.minimum(y0 + rng.integers(0, 3, n), tiles_y - 1)
    rects_np = np.stack([x0, y0, x1, y1], 1).astype(np.int32)
    rects_np[5] = (0, 0, -1, -1)  # a primitive on no tile
    counts_np = np.maximum(rects_np[:, 2] - rects_np[:, 0] + 1, 0) * np.maximum(rects_np[:, 3] - rects_np[:, 1] + 1, 0)
    order_np = rng.permutation(n).astype(np.int32)  # a depth order
    offsets_np = np.cumsum(counts_np[order_np]).astype(np.int32)
    total = int(offsets_np[-1])
    dev = "cpu"
    rects = wp.array(rects_np, dtype=wp.vec4i, device=dev)
    counts = wp.array(counts_np.astype(np.int32), dtype=wp.int32, device=dev)
    order = wp.array(order_np, dtype=wp.int32, device=dev)
    offsets = wp.array(offsets_np, dtype=wp.int32, device=dev)
    keys = wp.zeros(2 * total, dtype=wp.int32, device=dev)
    ids = wp.zeros(2 * total, dtype=wp.int32, device=dev)
    wp.launch(binning.emit_tile_keys, n, [rects, order, offsets, counts, tiles_x, keys, ids], device=dev)
    emitted = list(zip(keys.numpy()[:total], ids.numpy()[:total]))
    wp.utils.radix_sort_pairs(keys, ids, total)  # by tile: scrambles each primitive's pairs
    ranges = wp.zeros(n, dtype=wp.vec2i, device=dev)
    positions = wp.full(total, -1, dtype=wp.int32, device=dev)
    wp.launch(pair_sums.pair_ranges, n, [order, offsets, counts, ranges], device=dev)
    wp.launch(pair_sums.pair_positions, total, [ids, keys, rects, ranges, tiles_x, positions], device=dev)
    pos = positions.numpy()
    assert sorted(pos) == list(range(total))  # a permutation: every sorted pair found exactly once
    sorted_pairs = list(zip(keys.numpy()[:total], ids.numpy()[:total]))
    assert [sorted_pairs[p] for p in pos] == emitted  # emitted slot -> the same (tile, primitive) after the sort
    assert pos.tolist() != list(range(total))  # the sort did move pairs: the test means something

    magnitudes = 10.0 ** rng.integers(-3, 3, (total * parts, 1))  # mixed scales: the order of float32 adds matters
    values_np = (rng.standard_normal((total * parts, width)) * magnitudes).astype(np.float32)
    sums = wp.array(np.full(n * width, 0.5, np.float32), dtype=float, device=dev)  # adds to what is there
    wp.launch(pair_sums.sum_pair_parts, n * width,
              [positions, ranges, parts, width, wp.array(values_np.reshape(-1), dtype=float, device=dev), sums],
              device=dev)
    per_pair = values_np.astype(np.float64).reshape(total, parts, width).sum(1)
    want = np.full((n, width), 0.5)
    for k, (_, i) in enumerate(sorted_pairs):
        want[i] += per_pair[k]
    got = sums.numpy().reshape(n, width)
    scale = np.abs(values_np).max() * (counts_np.max() * parts)
    np.testing.assert_allclose(got, want, rtol=0, atol=scale * 2e-7 * 4)
    assert np.all(got[5] == 0.5)  # no pairs: untouched


def _grads(kind, deterministic, num_features=3):
    s = random_scene(n=90, width=56, height=40, seed=5, num_features=num_features)
    leaves = {k: s[k].float().clone().requires_grad_(True) for k in ("means", "quats", "opacities", "colors")}
    leaves["scales"] = (s["scales"][:, :2] if kind == "surfels" else s["scales"]).float().clone().requires_grad_(True)
    leaves["features"] = s["features"].float().clone().requires_grad_(True)
    op = rasterize_surfels if kind == "surfels" else rasterize
    outputs = ("rgb", "alpha", "depth", "features") + (("normal", "distortion") if kind == "surfels" else ())
    out = op(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"],
             s["viewmat"].float(), s["K"].float(), s["width"], s["height"], outputs=outputs,
             features=leaves["features"], deterministic=deterministic)
    g = torch.Generator().manual_seed(1)
    loss = sum((getattr(out, o) * torch.rand(getattr(out, o).shape, generator=g)).sum() for o in outputs)
    loss.backward()
    return {k: v.grad.clone() for k, v in leaves.items()}


@pytest.mark.skipif(not COOPERATIVE, reason="the GPU adjoints run on the CPU only with WARPGS_CPU_COOPERATIVE=1 "
                                            "(test_raster_gpu_kernels_on_cpu.py runs this file so)")
@pytest.mark.parametrize("kind", ["gaussians", "surfels"])
@pytest.mark.parametrize("variant", ["warp_sums", "block"])
def test_deterministic_adjoint_gives_the_default_gradients(kind, variant):
    option = "surfel_backward_kernel" if kind == "surfels" else "backward_kernel"
    with raster_options(**{option: variant}):
        default = _grads(kind, False)
        fixed = _grads(kind, True)
        again = _grads(kind, True)
    for k, ref in default.items():
        assert ref.abs().max() > 0, k  # every input gets a gradient: the comparison covers it
        torch.testing.assert_close(fixed[k], ref, rtol=1e-4, atol=1e-5 * ref.abs().max().item(),
                                   msg=lambda m, k=k: f"{kind} {variant} grad {k}: {m}")
        assert torch.equal(fixed[k], again[k]), k


def test_bad_settings_are_refused_by_name():
    from warpgs.train.determinism import use_deterministic_algorithms

    with pytest.raises(ValueError, match="raster option deterministic"):
        with raster_options(deterministic="yes"):
            pass
    was = torch.are_deterministic_algorithms_enabled()
    with pytest.raises(ValueError, match="train.deterministic.*train.parallel=model"):
        use_deterministic_algorithms(torch.device("cpu"), model_parallel=True)
    assert torch.are_deterministic_algorithms_enabled() == was  # refused before switching anything on
