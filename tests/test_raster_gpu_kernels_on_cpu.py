"""The block-cooperative GPU kernels (kernels/blend_gpu.py), run on the CPU through Warp's CPU blocks, must
pass the same forward and gradient checks: CI has no GPU, and these are the kernels GPUs run. Every GPU adjoint
(`backward_kernel_warp_sums` with its reduce-scatter sums, the default, and with lane 0's sums, `backward_kernel` with
and without its block sums, and the deterministic mode's twins) is checked against the float64 reference, and the op against its per-call oracle (tests/legacy_raster.py)."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).parent

VARIANTS = {  # name: (environment, test files)
    # the default (the per-warp adjoint with reduce-scatter sums) and, below, its lane-0 twin and the block adjoint
    "scatter": ({"WARPGS_BWD_KERNEL": "scatter"},
                ["test_raster_forward.py", "test_raster_gradients.py",
                 "test_raster_knobs.py",  # covers the surfel kernels at other thresholds too
                 "test_raster_degenerate.py", "test_raster_fast_path.py", "test_absgrad.py",
                 "test_render_splats.py"]),  # the split op of model-parallel rendering
    "warp_sums": ({"WARPGS_BWD_KERNEL": "warp_sums"},
                  ["test_raster_gradients.py",
                   "test_raster_knobs.py::test_gaussians_gradients_follow_reference_at_other_thresholds",
                   "test_absgrad.py"]),
    # the tile-key emission's full search (raster option pair_search; the default narrows it): the op against its oracle
    "pair_full": ({"WARPGS_PAIR_SEARCH": "full"}, ["test_raster_fast_path.py", "test_binning.py"]),
    # forward-only renders sorting their pairs ahead of their count (the GPU default; needs the cooperative kernels)
    "sort_ahead": ({}, ["test_sort_ahead.py"]),
    "block": ({"WARPGS_BWD_KERNEL": "block", "WARPGS_BLOCK_REDUCE": "1"},
              ["test_raster_gradients.py",
               "test_raster_knobs.py::test_gaussians_gradients_follow_reference_at_other_thresholds",
               "test_render_splats.py::test_projecting_then_blending_is_rasterize", "test_absgrad.py"]),
    "block-no-reduce": ({"WARPGS_BWD_KERNEL": "block", "WARPGS_BLOCK_REDUCE": "0"},
                        ["test_raster_gradients.py::test_gradients_of_all_inputs_match_reference",
                         "test_absgrad.py"]),
    # the fixed-order adjoint (raster option deterministic): the float64 checks, and the default path's gradients
    "deterministic": ({"WARPGS_DETERMINISTIC": "1"},
                      ["test_raster_gradients.py", "test_deterministic_gradients.py", "test_absgrad.py"]),
}  # the per-call oracle runs in test_raster_fast_path.py, as the reference of the op


@pytest.mark.skipif(os.environ.get("WARPGS_CPU_COOPERATIVE") == "1", reason="this run is cooperative already")
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_cooperative_kernels_match_the_reference(variant):
    extra, files = VARIANTS[variant]
    env = dict(os.environ, WARPGS_CPU_COOPERATIVE="1", **extra)
    tests = [str(HERE / f) for f in files]
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *tests],
                          env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert " passed" in proc.stdout
