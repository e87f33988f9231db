"""A training process killed with SIGKILL (no handler runs) loses at most one checkpoint interval: killed right
after a checkpoint, or half-way through writing the next one, `--resume` continues from the last complete
checkpoint and ends exactly where an uninterrupted run ends.

The kill moments are exact, not timed: WARPGS_ATOMIC_WRITE_GATE (warpgs/utils/atomic_file.py) makes the
training process stop at named points of each atomic write until this test lets it go, or kills it there."""
import os
import signal
import subprocess
import sys
import time

import torch

from train_fixtures import quick_overrides
from warpgs.cli.commands import train_main
from warpgs.train.checkpoint import leftover_temp_files, load_checkpoint
from warpgs.utils.atomic_file import GATE_ENV

STEPS, EVERY = 20, 5
TIMEOUT_S = 120


def _train_command(out, resume=False):
    args = quick_overrides(out, STEPS, **{"train.checkpoint_every": EVERY}) + ["--quiet"]
    return [sys.executable, "-m", "warpgs.cli", "train", "default"] + args + (["--resume"] if resume else [])


def _run_until_stop(out, gate, kill_at, resume=False):
    """Runs warpgs-train with the write gate in `gate`, opening every stop until `kill_at` (e.g.
    'checkpoint.pt.2.half') appears; then SIGKILLs the process there. Returns the stops seen, in order."""
    gate.mkdir()
    env = dict(os.environ, **{GATE_ENV: str(gate)})
    proc = subprocess.Popen(_train_command(out, resume), env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    seen, deadline = [], time.monotonic() + TIMEOUT_S
    try:
        while True:
            stops = sorted((p for p in gate.iterdir() if not p.name.endswith(".go") and p.name not in seen),
                           key=lambda p: p.stat().st_mtime_ns)
            for stop in stops:
                seen.append(stop.name)
                if stop.name == kill_at:
                    proc.send_signal(signal.SIGKILL)
                    proc.wait(TIMEOUT_S)
                    return seen
                (gate / (stop.name + ".go")).touch()
            if proc.poll() is not None:
                raise AssertionError(f"training ended (rc {proc.returncode}) before {kill_at}; stops {seen}\n"
                                     f"{proc.stdout.read().decode(errors='replace')[-3000:]}")
            assert time.monotonic() < deadline, f"no {kill_at} within {TIMEOUT_S} s; stops {seen}"
            time.sleep(0.005)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()


def test_sigkill_during_and_between_checkpoint_writes_then_resume(tmp_path):
    out = tmp_path / "run"

    # Killed between writes: just after the step-5 checkpoint was put in place.
    seen = _run_until_stop(out, tmp_path / "gate1", "checkpoint.pt.1.done")
    assert "checkpoint.pt.1.half" in seen
    assert load_checkpoint(out / "checkpoint.pt")["step"] == EVERY
    assert not leftover_temp_files(out)

    # Resumed at step 5, then killed half-way through writing the step-15 checkpoint (its 2nd write).
    _run_until_stop(out, tmp_path / "gate2", "checkpoint.pt.2.half", resume=True)
    assert load_checkpoint(out / "checkpoint.pt")["step"] == 2 * EVERY  # step 10: complete and readable
    (partial,) = leftover_temp_files(out)  # the half-written step-15 file, never renamed into place
    assert 0 < partial.stat().st_size < (out / "checkpoint.pt").stat().st_size

    # Resumed from step 10 (what the kill lost: steps 10-15, one interval), it runs to the end.
    done = subprocess.run(_train_command(out, resume=True), capture_output=True, text=True, timeout=TIMEOUT_S)
    assert done.returncode == 0, done.stdout + done.stderr
    final = load_checkpoint(out / "checkpoint.pt")
    assert final["step"] == STEPS

    # ... and ends exactly where an uninterrupted run of the same command does (CPU training is deterministic).
    assert train_main(["default"] + quick_overrides(tmp_path / "straight", STEPS) + ["--quiet"]) == 0
    straight = load_checkpoint(tmp_path / "straight" / "checkpoint.pt")
    for name, p in straight["model"]["params"].items():
        assert torch.equal(final["model"]["params"][name], p), name
