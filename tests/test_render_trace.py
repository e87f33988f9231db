"""benchmarks/render_trace.py: a render call's GPU time from trace events."""
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import render_trace  # noqa: E402


def test_only_what_happens_inside_the_calls_is_counted():
    calls = [{"cat": "user_annotation", "name": "call", "ts": t, "dur": 50} for t in (0, 100)]
    kernels = [{"cat": "kernel", "name": "blend", "ts": 10, "dur": 20},
               {"cat": "kernel", "name": "blend", "ts": 110, "dur": 30},
               {"cat": "kernel", "name": "outside", "ts": 70, "dur": 10}]  # between the calls: the profiler's own
    syncs = [{"cat": "cuda_runtime", "name": "cudaDeviceSynchronize", "ts": t, "dur": 1} for t in (45, 145, 300)]
    found = render_trace.per_call_breakdown(calls + kernels + syncs, calls=2)
    assert found["calls_seen"] == 2 and found["profiled_wall_us"] == 50
    assert found["gpu_busy_us"] == 25 and found["kernels_us_per_call"] == {"blend": 25}
    assert found["host_reads_per_call"] == {"cudaDeviceSynchronize": 1.0}


def test_cub_kernels_are_told_apart_past_their_shared_prefix():
    sort = "void cub::_V_300403_SM_750_800_860_890_900_1000_1200_1210::detail::radix_sort::DeviceRadixSortOnesweep<x>"
    scan = "void cub::_V_300403_SM_750_800_860_890_900_1000_1200_1210::detail::scan::DeviceScanKernel<x>"
    assert render_trace.kernel_name(sort).startswith("cub::detail::radix_sort::")
    assert render_trace.kernel_name(scan).startswith("cub::detail::scan::")
    assert render_trace.kernel_name("blend_forward_blocks") == "blend_forward_blocks"
