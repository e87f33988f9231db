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
    assert found["syncs_per_call"] == {"cudaDeviceSynchronize": 1.0} and found["reads_per_call"] == 0


def test_reads_are_device_to_host_copies_whatever_api_issued_them():
    """Warp reads its tile-pair count through the driver API, which the runtime rows never show; the copy itself is
    on the GPU's side of the trace. Device-to-device staging copies are no read."""
    calls = [{"cat": "user_annotation", "name": "call", "ts": t, "dur": 50} for t in (0, 100)]
    per_call = (("Memcpy DtoH (Device -> Pinned)", 20), ("Memcpy DtoD (Device -> Device)", 5),
                ("Memcpy DtoD (Device -> Device)", 6))
    copies = [{"cat": "gpu_memcpy", "name": name, "ts": start + at, "dur": 2}
              for start in (0, 100) for name, at in per_call]
    runtime = [{"cat": "cuda_runtime", "name": "cudaMemcpyAsync", "ts": t, "dur": 1} for t in (4, 104)]
    found = render_trace.per_call_breakdown(calls + copies + runtime, calls=2)
    assert found["reads_per_call"] == 1.0
    assert found["copies_per_call"] == {"DtoH": 1.0, "DtoD": 2.0}
    assert found["syncs_per_call"] == {}


def test_cub_kernels_are_told_apart_past_their_shared_prefix():
    sort = "void cub::_V_300403_SM_750_800_860_890_900_1000_1200_1210::detail::radix_sort::DeviceRadixSortOnesweep<x>"
    scan = "void cub::_V_300403_SM_750_800_860_890_900_1000_1200_1210::detail::scan::DeviceScanKernel<x>"
    assert render_trace.kernel_name(sort).startswith("cub::detail::radix_sort::")
    assert render_trace.kernel_name(scan).startswith("cub::detail::scan::")
    assert render_trace.kernel_name("blend_forward_blocks") == "blend_forward_blocks"


def test_a_calls_gpu_waits_are_placed_before_the_work_they_delay():
    """Idle time is measured from the call's start or the end of all earlier work (overlapping kernels do not make
    a wait), and the wait after the last kernel is the call's own tail."""
    events = [{"cat": "kernel", "name": "project", "ts": 110, "dur": 5},
              {"cat": "kernel", "name": "sort", "ts": 140, "dur": 30},
              {"cat": "kernel", "name": "overlapping", "ts": 150, "dur": 10},
              {"cat": "kernel", "name": "blend", "ts": 180, "dur": 10}]
    timeline = render_trace.idle_before(events, 100, 200)
    assert [(name, idle) for name, idle, _ in timeline] == [
        ("project", 10), ("sort", 25), ("overlapping", 0), ("blend", 10), ("(end)", 10)]


def test_the_typical_call_is_the_one_with_the_median_wait():
    calls = [{"cat": "user_annotation", "name": "call", "ts": t, "dur": 100} for t in (0, 200, 400)]
    kernels = [{"cat": "kernel", "name": "blend", "ts": t + 10, "dur": busy}
               for t, busy in ((0, 80), (200, 10), (400, 40))]  # waits 20, 90, 60
    found = render_trace.per_call_breakdown(calls + kernels, calls=3)
    assert found["typical_call_timeline"] == [["blend", 10.0, 40.0], ["(end)", 50.0, 0.0]]


def test_host_work_before_the_gpu_starts_counts_outer_events_once_and_the_rest_as_python():
    host = [{"cat": "cpu_op", "name": "aten::copy_", "ts": 10, "dur": 20},
            {"cat": "cuda_runtime", "name": "cudaMemcpyAsync", "ts": 15, "dur": 5},  # inside copy_: not again
            {"cat": "cuda_driver", "name": "cuGraphLaunch", "ts": 60, "dur": 10},
            {"cat": "cpu_op", "name": "aten::empty", "ts": 95, "dur": 10}]  # ends after the GPU started: left out
    found = render_trace.host_before_first_work(host, 0, 100)
    assert found == {"(not seen: Python)": 70.0, "aten::copy_": 20.0, "cuGraphLaunch": 10.0}


def test_the_typical_calls_host_work_is_reported_with_its_timeline():
    calls = [{"cat": "user_annotation", "name": "call", "ts": t, "dur": 100} for t in (0, 200)]
    kernels = [{"cat": "kernel", "name": "blend", "ts": t + 40, "dur": 10} for t in (0, 200)]
    host = [{"cat": "cpu_op", "name": "aten::copy_", "ts": t + 5, "dur": 20} for t in (0, 200)]
    found = render_trace.per_call_breakdown(calls + kernels + host, calls=2)
    assert found["typical_call_host_before_gpu"] == {"aten::copy_": 20.0, "(not seen: Python)": 20.0}
