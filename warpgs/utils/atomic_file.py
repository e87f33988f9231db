"""Atomic file writes: readers see the old file or the new one, never a half-written one.

For crash tests, WARPGS_ATOMIC_WRITE_GATE=<folder> makes every write stop at three points and wait for the
test: "start" (nothing written yet), "half" (half the bytes in the temp file) and "done" (the new file in
place). At each point the writer creates `<folder>/<name>.<k>.<point>` (name: the target's file name, k: its
1-based write count in this process) and waits until `<folder>/<name>.<k>.<point>.go` exists, so a test can
kill the process at an exact moment instead of sleeping and hoping. Never set outside tests.
"""
from __future__ import annotations

import os
import tempfile
import time

GATE_ENV = "WARPGS_ATOMIC_WRITE_GATE"
GATE_TIMEOUT_S = 300.0  # a gate nobody opens fails the write instead of hanging forever
_writes: dict = {}


def atomic_write_bytes(path, payload: bytes) -> None:
    """Readers see the old file or the new one, never half of one (also on Ctrl-C)."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    gate = _Gate.for_write(path)
    gate.wait("start")
    fd, tmp = tempfile.mkstemp(dir=folder, prefix="." + os.path.basename(path) + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            if gate.active:  # the "half" stop: half the payload on disk, as a crash mid-write would leave it
                f.write(payload[: len(payload) // 2])
                f.flush()
                os.fsync(f.fileno())
                gate.wait("half")
                f.write(payload[len(payload) // 2:])
            else:
                f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes 0600 files; a saved model should be readable like any other
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    gate.wait("done")


class _Gate:
    """The WARPGS_ATOMIC_WRITE_GATE stops of one write (inactive when the variable is not set)."""

    def __init__(self, folder, name: str = "", count: int = 0):
        self.folder, self.name, self.count = folder, name, count
        self.active = folder is not None

    @classmethod
    def for_write(cls, path: str) -> "_Gate":
        folder = os.environ.get(GATE_ENV)
        if not folder:
            return cls(None)
        name = os.path.basename(path)
        _writes[name] = _writes.get(name, 0) + 1
        return cls(folder, name, _writes[name])

    def wait(self, point: str) -> None:
        if not self.active:
            return
        stop = os.path.join(self.folder, f"{self.name}.{self.count}.{point}")
        with open(stop, "w"):
            pass
        deadline = time.monotonic() + GATE_TIMEOUT_S
        while not os.path.exists(stop + ".go"):
            if time.monotonic() > deadline:
                raise TimeoutError(f"{GATE_ENV}: {stop}.go did not appear within {GATE_TIMEOUT_S:.0f} s")
            time.sleep(0.005)
