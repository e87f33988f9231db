"""kernels/warp_ops.py's reduce-scatters: on the CPU (Warp's CPU blocks, the branch CI runs) every lane gets the warp's
sum of its own entry, and so does the generated GPU code, run line by line over emulated lanes; compiled for a GPU
(ahead of time, which needs no GPU), the adjoints that use them keep their values in registers (a version whose
values went to local memory made the 3D call 1.6x slower on an H200) with fewer shuffles and atomics than the
lane-0 sums they replace; and each kernel's gradient layout is the host's."""
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


def _field_offsets(fields) -> dict:
    """{name: (offset in N, floats per primitive)} of a blend adjoint's own fields, in the block run_blend_adjoint
    lays out (the caller's opacity and feature arrays take no room there)."""
    offsets, at = {}, 0
    for f in fields:
        if isinstance(f, tuple):
            offsets[f[0]] = (at, f[1])
            at += f[1]
    return offsets


@pytest.mark.parametrize("kernels,names", [
    (blend_gpu, ["means2d"] * 2 + ["conics"] * 3 + [None] + ["colors"] * 3 + ["depths"]),
    (surfel_blend_gpu, ["transforms"] * 9 + ["means2d"] * 2 + ["depths"] + [None] + ["colors"] * 3 + ["normals"] * 3),
], ids=["gaussians", "surfels"])
def test_scatter_slots_follow_the_host_layout_of_the_gradient_block(kernels, names):
    """Entry k of a gradient row lands where the host's fields put it: SCATTER_LAYOUT against the fields list the
    pipeline hands run_blend_adjoint, and the kernel's scatter_slot against SCATTER_LAYOUT (None: the opacity)."""
    from warpgs.render import fast_pipeline, fast_pipeline_surfels
    fields = (fast_pipeline_surfels if kernels is surfel_blend_gpu else fast_pipeline).ADJOINT_FIELDS
    offsets = _field_offsets(fields)
    seen = {}
    for k, (name, layout) in enumerate(zip(names, kernels.SCATTER_LAYOUT)):
        assert (layout is None) == (name is None), k
        if name is not None:
            component = seen[name] = seen.get(name, -1) + 1
            assert layout == (offsets[name][0], offsets[name][1], component), k

    n, g = 7, 3
    slots = wp.zeros(len(names), dtype=int, device="cpu")

    @wp.kernel(module="unique")
    def slot_of(out: wp.array(dtype=int)):
        k = wp.tid()
        out[k] = kernels.scatter_slot(k, g, n)
    wp.launch(slot_of, dim=len(names), inputs=[slots], device="cpu")
    for k, layout in enumerate(kernels.SCATTER_LAYOUT):
        if layout is not None:
            assert slots.numpy()[k] == layout[0] * n + layout[1] * g + layout[2], k


@pytest.mark.parametrize("width", [16, 32])
def test_generated_gpu_butterfly_leaves_each_lane_its_entrys_sum(width):
    """The GPU branch of the scatter (generated code CI cannot run), executed line by line over 32 emulated lanes:
    each `WPGS_KEEP(bit, lo, hi)` keeps `hi` in lanes with that bit set and adds the partner lane's other half."""
    from warpgs.kernels.warp_ops import _scatter_snippet
    code = _scatter_snippet(width)
    gpu = code[code.index("#if defined(__CUDA_ARCH__)"): code.index("#else")]
    x = np.random.default_rng(1).normal(size=(32, width))
    lanes = np.arange(32)
    values = {f"x[{i}]": x[:, i] for i in range(width)}

    def shfl_xor(v, bit):
        return v[lanes ^ bit]
    result = None
    for line in gpu.splitlines():
        keep = re.match(r"\s*const float (\w+) = WPGS_KEEP\((\d+), ([\w\[\]]+), ([\w\[\]]+)\);", line)
        if keep:
            name, bit, lo, hi = keep.group(1), int(keep.group(2)), values[keep.group(3)], values[keep.group(4)]
            upper = (lanes & bit) != 0
            values[name] = np.where(upper, hi, lo) + shfl_xor(np.where(upper, lo, hi), bit)
        ret = re.match(r"\s*return (\w+)(?: \+ __shfl_xor_sync\(0xffffffffu, (\w+), 1\))?;", line)
        if ret:
            result = values[ret.group(1)] + (shfl_xor(values[ret.group(2)], 1) if ret.group(2) else 0.0)
    assert result is not None
    entry = (lanes >> 1) & 15 if width == 16 else lanes
    np.testing.assert_allclose(result, x.sum(axis=0)[entry], rtol=1e-12, atol=1e-12)
