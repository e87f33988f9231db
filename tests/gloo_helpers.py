"""Two gloo processes for a test: a worker script started as rank 0 and rank 1 with torchrun's environment (no
torchrun agent), each bounded by a timeout so a hang fails the test instead of stalling CI."""
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def end_worker() -> None:
    """The last line of a worker script, once its results are saved: the process group destroyed, then the process
    ended without the interpreter's teardown, where gloo still aborts a process now and then after a clean run
    ("terminate called without an active exception", seen on CI after warpgs' own shutdown_process_group)."""
    from warpgs.train.distributed import shutdown_process_group

    shutdown_process_group()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_two_ranks(script: str, args: list, tmp_path: Path, timeout: float = 300.0) -> None:
    """Writes `script` to tmp_path and runs it as ranks 0 and 1 (argv: the script, then `args`); asserts both
    exit 0, showing the stderr of a rank that did not."""
    path = tmp_path / "worker.py"
    path.write_text(script)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")]),
               OMP_NUM_THREADS="1", WORLD_SIZE="2", MASTER_ADDR="127.0.0.1", MASTER_PORT=str(free_port()))
    results = start_two_ranks([sys.executable, str(path), *map(str, args)], env, timeout)
    for rank, (code, _, err) in enumerate(results):
        assert code == 0, f"rank {rank}: {err[-3000:]}"


def start_two_ranks(argv: list, env: dict, timeout: float) -> list:
    """Runs `argv` as ranks 0 and 1 (env gets RANK and LOCAL_RANK; the caller gives the rest of torchrun's
    environment) and waits for both, killing what is still running `timeout` seconds after the start (so a hang
    fails the test instead of stalling CI). Returns [(returncode, stdout, stderr)] per rank."""
    procs = [subprocess.Popen(argv, env=dict(env, RANK=str(r), LOCAL_RANK=str(r)), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for r in (0, 1)]
    return wait_all(procs, time.monotonic() + timeout)


def wait_all(procs: list, deadline: float) -> list:
    """Waits for every process (started with text pipes) until `deadline` (time.monotonic()), killing what is still
    running then. Returns [(returncode, stdout, stderr)] per process."""
    try:
        outputs = [p.communicate(timeout=max(1.0, deadline - time.monotonic())) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    return [(p.returncode, out, err) for p, (out, err) in zip(procs, outputs)]
