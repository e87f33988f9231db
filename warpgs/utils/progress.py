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
