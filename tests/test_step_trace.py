"""benchmarks/step_trace.py: the GPU's busy time and the host reads, from trace events."""
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import step_trace  # noqa: E402


def test_busy_time_is_the_union_of_overlapping_gpu_intervals():
    events = [{"cat": "kernel", "ts": 0, "dur": 10}, {"cat": "kernel", "ts": 5, "dur": 10},
              {"cat": "gpu_memcpy", "ts": 30, "dur": 5}, {"cat": "cpu_op", "ts": 0, "dur": 100}]
    assert step_trace.busy_time(events) == (35, 20)
    assert step_trace.busy_time([{"cat": "cpu_op", "ts": 0, "dur": 1}]) == (0.0, 0.0)


def test_host_reads_are_counted_per_step_at_their_innermost_warpgs_frames():
    frames = [{"cat": "python_function", "tid": 1, "ts": 0, "dur": 100, "name": "warpgs/train/step.py(16): train_step"},
              {"cat": "python_function", "tid": 1, "ts": 10, "dur": 20, "name": "warpgs/train/guard.py(29): check"},
              {"cat": "python_function", "tid": 1, "ts": 12, "dur": 5, "name": "torch/x.py(1): item"}]
    calls = [{"cat": "cuda_runtime", "tid": 1, "ts": 14, "dur": 7, "name": "cudaStreamSynchronize"},
             {"cat": "cuda_runtime", "tid": 1, "ts": 50, "dur": 3, "name": "cudaMemcpyAsync"},
             {"cat": "cuda_runtime", "tid": 1, "ts": 60, "dur": 9, "name": "cudaLaunchKernel"}]
    rows = step_trace.host_reads(frames + calls + calls, steps=2)
    assert [(r["call"], r["per_step"], r["host_us_per_step"]) for r in rows] == [
        ("cudaStreamSynchronize", 1.0, 7.0), ("cudaMemcpyAsync", 1.0, 3.0)]
    assert rows[0]["site"] == "warpgs/train/guard.py(29): check < warpgs/train/step.py(16): train_step"
    assert rows[1]["site"] == "warpgs/train/step.py(16): train_step"


def test_gpu_idle_gaps_go_to_the_launch_that_ended_them():
    frames = [{"cat": "python_function", "tid": 1, "ts": 0, "dur": 100, "name": "warpgs/train/step.py(16): train_step"},
              {"cat": "python_function", "tid": 1, "ts": 40, "dur": 10, "name": "warpgs/losses/photometric.py(9): l1"}]
    launches = [{"cat": "cuda_runtime", "tid": 1, "ts": 2, "dur": 1, "name": "cudaLaunchKernel",
                 "args": {"correlation": 1}},
                {"cat": "cuda_runtime", "tid": 1, "ts": 45, "dur": 1, "name": "cudaLaunchKernel",
                 "args": {"correlation": 2}},
                {"cat": "cuda_runtime", "tid": 1, "ts": 42, "dur": 1, "name": "cudaMemcpyAsync"}]
    kernels = [{"cat": "kernel", "ts": 5, "dur": 10, "args": {"correlation": 1}},
               {"cat": "kernel", "ts": 16, "dur": 4, "args": {"correlation": 9}},  # 1 us after: no gap
               {"cat": "kernel", "ts": 48, "dur": 2, "args": {"correlation": 2}},  # 28 us idle: the l1 launch
               {"cat": "kernel", "ts": 75, "dur": 5, "args": {}}]  # 25 us idle, launch unseen: frames at 74
    rows = step_trace.gpu_waits(frames + launches + kernels, steps=1)
    assert [(r["site"], r["gaps_per_step"], r["idle_us_per_step"]) for r in rows] == [
        ("warpgs/losses/photometric.py(9): l1 < warpgs/train/step.py(16): train_step", 1.0, 28.0),
        ("warpgs/train/step.py(16): train_step", 1.0, 25.0)]


def test_a_gap_before_an_already_queued_kernel_is_not_a_host_wait():
    launches = [{"cat": "cuda_runtime", "tid": 1, "ts": ts, "dur": 1, "name": "cudaLaunchKernel",
                 "args": {"correlation": c}} for ts, c in ((1, 1), (2, 2))]
    kernels = [{"cat": "kernel", "ts": 5, "dur": 5, "args": {"correlation": 1}},
               {"cat": "kernel", "ts": 30, "dur": 5, "args": {"correlation": 2}}]  # queued at 2, idle 10..30
    rows = step_trace.gpu_waits(launches + kernels, steps=1)
    assert rows == [{"site": "(launched before the gap: not a wait for the host)", "gaps_per_step": 1.0,
                     "idle_us_per_step": 20.0}]


def test_warps_waits_are_found_by_their_python_frames():
    frames = [{"cat": "python_function", "tid": 1, "ts": ts, "dur": dur, "name": name} for ts, dur, name in (
        (0, 100, "warpgs/render/workspace.py(352): run"), (10, 40, "warp/_src/context.py(9): synchronize_stream"),
        (60, 5, "warp/_src/context.py(9): launch"))]
    later = [dict(f, ts=f["ts"] + 200) for f in frames]  # the second step
    rows = step_trace.warp_waits(frames + later, steps=2)
    assert rows == [{"site": "warpgs/render/workspace.py(352): run", "per_step": 1.0, "host_us_per_step": 40.0}]
