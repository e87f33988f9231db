"""The block-cooperative surfel kernels (kernels/surfel_blend_gpu.py), run on the CPU through Warp's CPU
blocks, must pass the same forward and gradient checks: CI has no GPU, and these are the kernels GPUs run. Every
GPU adjoint (`backward_kernel` with and without its block sums, `backward_kernel_warp_sums` with lane 0's sums and
with reduce-scatter sums, and the deterministic mode's twin of the default) is checked against the float64 reference."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).parent


VARIANTS = {  # name: (environment, test files)
    "block": ({"WARPGS_SURFEL_BWD_KERNEL": "block", "WARPGS_BLOCK_REDUCE": "1"},
              ["test_surfels_forward.py", "test_surfels_gradients.py",
               "test_surfels_fast_path.py"]),  # the per-call oracle there runs the same kernels
    "block-no-reduce": ({"WARPGS_SURFEL_BWD_KERNEL": "block", "WARPGS_BLOCK_REDUCE": "0"},  # only the backward differs
                        ["test_surfels_gradients.py::test_gradients_of_all_inputs_through_all_outputs"]),
    "warp_sums": ({"WARPGS_SURFEL_BWD_KERNEL": "warp_sums"}, ["test_surfels_gradients.py"]),
    # the per-warp adjoint with its sums by a 32-value reduce-scatter (raster option surfel_backward_kernel="scatter")
    "scatter": ({"WARPGS_SURFEL_BWD_KERNEL": "scatter"}, ["test_surfels_gradients.py", "test_surfels_fast_path.py"]),
    "deterministic": ({"WARPGS_DETERMINISTIC": "1"}, ["test_surfels_gradients.py"]),  # the fixed-order adjoint
    "pair_full": ({"WARPGS_PAIR_SEARCH": "full"}, ["test_surfels_fast_path.py"]),  # the tile keys' full search
}


@pytest.mark.skipif(os.environ.get("WARPGS_CPU_COOPERATIVE") == "1", reason="this run is cooperative already")
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_cooperative_surfel_kernels_match_the_reference(variant):
    extra, files = VARIANTS[variant]
    env = dict(os.environ, WARPGS_CPU_COOPERATIVE="1", **extra)
    tests = [str(HERE / f) for f in files]
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *tests],
                          env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert " passed" in proc.stdout
