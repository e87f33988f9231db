"""Run benchmark processes side by side: at most `at_once` per group (a GPU, or one group for all), each with its
own log, reported as each one ends. The first failure stops the others and shows the end of its log; with
keep_going, a failure is reported (the end of its log) and the other jobs go on.

Used by ablation_jobs.py, real_capture_jobs.py and sparse.py (few-view and real-capture runs leave a GPU mostly
idle, so several share one)."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple


@dataclass
class Job:
    name: str  # also the log's file name: <log_dir>/<name>.log
    cmd: List[str]
    group: str = ""  # jobs of one group share its `at_once` slots (e.g. one GPU)
    env: Dict[str, str] = field(default_factory=dict)  # added to the environment


def parse_seeds_gpus(seeds: str, gpus: str, per_gpu: int) -> Tuple[List[int], List[int]]:
    """A wave driver's --seeds, --gpus (comma-separated integers; none: one group) and --per-gpu (at least 1)."""
    try:
        seed_list = [int(s) for s in seeds.split(",")]
        gpu_list = [int(g) for g in gpus.split(",")] if gpus else []
    except ValueError as e:
        raise SystemExit(f"--seeds / --gpus: comma-separated integers expected ({e})")
    if per_gpu < 1:
        raise SystemExit(f"--per-gpu: expected at least 1, got {per_gpu}")
    return seed_list, gpu_list


def gpu_slot(gpus: List[int], i: int) -> Tuple[str, Dict[str, str]]:
    """The i-th job's group and environment: round-robin over `gpus`, or one group that leaves
    CUDA_VISIBLE_DEVICES alone when there are none."""
    if not gpus:
        return "", {}
    group = str(gpus[i % len(gpus)])
    return group, {"CUDA_VISIBLE_DEVICES": group}


def run_jobs(jobs: List[Job], at_once: int, log_dir: Path, *, env: Optional[dict] = None,
             summary: Callable[[Job, str], str] = lambda job, log: job.name, poll_seconds: float = 1.0,
             keep_going: bool = False) -> List[Job]:
    """Runs every job (in order, as slots free up) and returns the ones that succeeded, in the order they ended.
    summary(job, log text) is the line printed (to stderr) when a job ends. A failure stops the rest (SystemExit
    with the end of its log), or with keep_going is printed and left out of the returned list."""
    if at_once < 1:
        raise ValueError(f"at_once: expected at least 1, got {at_once}")
    names = [j.name for j in jobs]
    if len(set(names)) != len(names):
        raise ValueError(f"job names must differ (they name the logs): {names}")
    log_dir = Path(log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    base = dict(os.environ if env is None else env)
    waiting, running, done = list(jobs), {}, []
    start = time.perf_counter()
    while waiting or running:
        for job in list(waiting):
            if sum(1 for j, _, _ in running.values() if j.group == job.group) < at_once:
                waiting.remove(job)
                log = open(log_dir / f"{job.name}.log", "w")
                proc = subprocess.Popen(job.cmd, stdout=log, stderr=subprocess.STDOUT, env={**base, **job.env})
                running[job.name] = (job, proc, log)
        for name, (job, proc, log) in list(running.items()):
            if proc.poll() is None:
                continue
            log.close()
            del running[name]
            text = (log_dir / f"{name}.log").read_text()
            if proc.returncode != 0:
                failure = f"{name} failed (exit {proc.returncode}); the end of its log:\n{text[-2000:]}"
                if keep_going:
                    print(f"  [{time.perf_counter() - start:6.0f} s] {failure}", file=sys.stderr, flush=True)
                    continue
                for _, other, _ in running.values():
                    other.terminate()
                raise SystemExit(failure)
            print(f"  [{time.perf_counter() - start:6.0f} s] {summary(job, text)}", file=sys.stderr, flush=True)
            done.append(job)
        if waiting or running:
            time.sleep(poll_seconds)
    return done


def detach(cmd: List[str], log: Path) -> int:
    """Start `cmd` in a new process session with its output in `log`, write its pid beside it (`<log>.pid`) and
    return the pid at once. A remote machine's command runner ends the processes a command leaves behind, except
    those in a session of their own, so a wave longer than one command must start this way."""
    log = Path(log)
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True)
    Path(f"{log}.pid").write_text(f"{proc.pid}\n")
    return proc.pid
