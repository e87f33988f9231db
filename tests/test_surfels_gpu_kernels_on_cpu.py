"""The block-cooperative surfel kernels (kernels/surfel_blend_gpu.py), run on the CPU through Warp's CPU
blocks, must pass the same forward and gradient checks: CI has no GPU, and these are the kernels GPUs run."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).parent


@pytest.mark.skipif(os.environ.get("WARPGS_CPU_COOPERATIVE") == "1", reason="this run is cooperative already")
@pytest.mark.parametrize("block_reduce", ["1", "0"])
def test_cooperative_surfel_kernels_match_the_reference(block_reduce):
    env = dict(os.environ, WARPGS_CPU_COOPERATIVE="1", WARPGS_BLOCK_REDUCE=block_reduce)
    tests = [str(HERE / "test_surfels_forward.py"), str(HERE / "test_surfels_gradients.py")]
    if block_reduce == "0":  # only the backward differs
        tests = [str(HERE / "test_surfels_gradients.py") + "::test_gradients_of_all_inputs_through_all_outputs"]
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *tests],
                          env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert " passed" in proc.stdout
