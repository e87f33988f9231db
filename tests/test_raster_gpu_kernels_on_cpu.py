"""The block-cooperative GPU kernels (kernels/blend_gpu.py), run on the CPU through Warp's CPU blocks, must
pass the same forward and gradient checks: CI has no GPU, and these are the kernels GPUs run."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).parent


@pytest.mark.parametrize("block_reduce", ["1", "0"])
def test_cooperative_kernels_match_the_reference(block_reduce):
    env = dict(os.environ, WARPGS_CPU_COOPERATIVE="1", WARPGS_BLOCK_REDUCE=block_reduce)
    tests = [str(HERE / "test_raster_forward.py"), str(HERE / "test_raster_gradients.py"),
             str(HERE / "test_raster_knobs.py")]  # the knobs file covers the surfel kernels at other thresholds too
    if block_reduce == "0":
        tests = [str(HERE / "test_raster_gradients.py") + "::test_gradients_of_all_inputs_match_reference"]
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *tests],
                          env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert " passed" in proc.stdout
