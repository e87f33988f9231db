"""A dependency-free progress line: redrawn in place (carriage return) on a terminal, one line every
`log_every` steps otherwise (logs, CI)."""
from __future__ import annotations

import sys
import time
from typing import Optional, TextIO


def _fmt_seconds(s: float) -> str:
    s = int(max(0, s))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60:d}:{s % 60:02d}"


class Progress:
    def __init__(self, total: int, start: int = 0, *, stream: Optional[TextIO] = None, enabled: bool = True,
                 log_every: int = 100, min_interval: float = 0.2, interactive: Optional[bool] = None):
        self.total, self.start = int(total), int(start)
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.log_every = max(1, int(log_every))
        self.min_interval = min_interval
        isatty = getattr(self.stream, "isatty", lambda: False)
        self.interactive = bool(isatty()) if interactive is None else interactive
        self.t0 = time.perf_counter()
        self._last_draw = 0.0
        self._rate = None  # steps/s, smoothed
        self._last = (self.t0, self.start)
        self._width = 0

    def update(self, step: int, **fields) -> None:
        """`step` = steps done; fields (loss, psnr, n, ...) are shown as given (floats with 4 significant digits)."""
        if not self.enabled:
            return
        now = time.perf_counter()
        t_prev, s_prev = self._last
        if step > s_prev and now > t_prev:
            inst = (step - s_prev) / (now - t_prev)
            self._rate = inst if self._rate is None else 0.8 * self._rate + 0.2 * inst
            self._last = (now, step)
        done = step >= self.total
        if self.interactive:
            if not done and now - self._last_draw < self.min_interval:
                return
            self._draw("\r" + self._line(step, fields), end="\n" if done else "")
        elif done or step % self.log_every == 0:
            self._draw(self._line(step, fields), end="\n")
        self._last_draw = now

    def _line(self, step: int, fields: dict) -> str:
        frac = step / max(self.total, 1)
        bar_len = 20
        filled = int(bar_len * frac)
        bar = "#" * filled + "-" * (bar_len - filled)
        rate = self._rate or 0.0
        eta = (self.total - step) / rate if rate > 0 else 0.0
        parts = [f"{step:>{len(str(self.total))}}/{self.total} [{bar}] {rate:5.1f} it/s eta {_fmt_seconds(eta)}"]
        for k, v in fields.items():
            if v is None:
                continue
            parts.append(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}")
        return " | ".join(parts)

    def _draw(self, text: str, end: str) -> None:
        pad = max(0, self._width - len(text)) if text.startswith("\r") else 0
        self.stream.write(text + " " * pad + end)
        self.stream.flush()
        self._width = 0 if end == "\n" else len(text)

    def write(self, message: str) -> None:
        """Print a message on its own line (above the progress line on a terminal)."""
        if self.interactive and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self._width = 0
            self._last_draw = 0.0  # redraw on the next update
        self.stream.write(message + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.interactive and self._width:
            self.stream.write("\n")
            self.stream.flush()
            self._width = 0


class Stages:
    """Per-stage progress of a multi-stage job (SfM: features, matching, triangulation, ...), on the same stream
    and in the same style as the training line:

        stages = Stages(["features", "matching", "mapping"], prefix="sfm")
        with stages.run("features", detail="292 images, max 1600 px"):
            ...                                   # prints "sfm [1/3] features (292 images, ...) ..." then "done in 12 s"
        stages.report("registered 290/292 images") # a free line in between

    `times` maps each finished stage to its wall time in seconds (for benchmarks and logs)."""

    def __init__(self, names, *, prefix: str = "warpgs", stream: Optional[TextIO] = None, enabled: bool = True):
        self.names = list(names)
        self.prefix = prefix
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.times: dict = {}

    def _say(self, text: str) -> None:
        if self.enabled:
            self.stream.write(text + "\n")
            self.stream.flush()

    def report(self, message: str) -> None:
        self._say(f"{self.prefix}: {message}")

    def run(self, name: str, detail: str = ""):
        return _Stage(self, name, detail)


class _Stage:
    def __init__(self, stages: Stages, name: str, detail: str):
        self.stages, self.name, self.detail = stages, name, detail

    def __enter__(self):
        s = self.stages
        index = s.names.index(self.name) + 1 if self.name in s.names else len(s.times) + 1
        detail = f" ({self.detail})" if self.detail else ""
        s._say(f"{s.prefix} [{index}/{max(len(s.names), index)}] {self.name}{detail} ...")
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, exc_type, exc, tb):
        elapsed = time.perf_counter() - self.t0
        self.stages.times[self.name] = elapsed
        status = "failed" if exc_type is not None else "done"
        self.stages._say(f"{self.stages.prefix} [{self.name}] {status} in {_fmt_seconds(elapsed)}")
        return False
