"""kernels/warp_ops.py's reduce-scatters: on the CPU (Warp's CPU blocks, the branch CI runs) every lane gets the warp's
sum of its own entry; compiled for a GPU (ahead of time, which needs no GPU), the adjoints that use them keep their
values in registers (a version whose values went to local memory made the 3D call 1.6x slower on an H200) with
fewer shuffles and atomics than the lane-0 sums they replace."""
import re

import numpy as np
import pytest
import warp as wp

from warpgs.kernels import blend_gpu, surfel_blend_gpu
from warpgs.kernels.warp_ops import Lanes16, Lanes32, lane_scatter_sum, lane_scatter_sum32

wp.config.enable_cpu_blocks = True  # Warp runs a CPU kernel as blocks only when asked


@wp.kernel(module="unique", module_options={"block_dim": 64})
def _scatter_both(values: wp.array2d(dtype=float), out16: wp.array(dtype=float), out32: wp.array(dtype=float)):
    tid = wp.tid()
    wp.tile_max(wp.tile(tid))  # a tile op: the CPU runs the kernel as cooperative blocks
    a = Lanes16()
    b = Lanes32()
    for i in range(16):
        a[i] = values[tid, i]
    for i in range(32):
        b[i] = values[tid, i]
    out16[tid] = lane_scatter_sum(a, tid % 32)
    out32[tid] = lane_scatter_sum32(b, tid % 32)


def test_each_lane_gets_the_warps_sum_of_its_entry():
    x = np.random.default_rng(0).normal(size=(64, 32)).astype(np.float32)
    out16, out32 = (wp.zeros(64, dtype=float, device="cpu") for _ in range(2))
    wp.launch(_scatter_both, dim=64, inputs=[wp.array(x, dtype=float, device="cpu"), out16, out32], block_dim=64,
              device="cpu")
    for t in range(64):
        warp_rows = x[32 * (t // 32): 32 * (t // 32) + 32]
        lane = t % 32
        assert out16.numpy()[t] == pytest.approx(warp_rows[:, (lane >> 1) & 15].sum(), abs=1e-4)
        assert out32.numpy()[t] == pytest.approx(warp_rows[:, lane].sum(), abs=1e-4)


def _ptx(kernel, name, tmp_path) -> str:
    try:
        path = wp.compile_aot_module(kernel.module, arch=90, module_dir=str(tmp_path / name), use_ptx=True)[0]
    except Exception as e:  # a Warp build without NVRTC cannot compile for a GPU here
        pytest.skip(f"no ahead-of-time CUDA compile on this machine: {e}")
    return path.read_text()


@pytest.mark.parametrize("kernels", [blend_gpu, surfel_blend_gpu], ids=["gaussians", "surfels"])
def test_scatter_adjoint_compiles_to_registers_with_fewer_shuffles_and_atomics(kernels, tmp_path):
    lane0 = _ptx(kernels.backward_kernel_warp_sums(64, 0), "lane0", tmp_path)
    scatter = _ptx(kernels.backward_kernel_warp_sums(64, 0, scatter=True), "scatter", tmp_path)
    assert ".local" not in scatter
    assert scatter.count("shfl.sync") < lane0.count("shfl.sync") / 2

    def atomics(ptx):
        return len(re.findall(r"^\s*(?:atom|red)\.", ptx, re.M))
    assert atomics(scatter) < atomics(lane0) / 2
