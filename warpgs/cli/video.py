"""MP4 output for `warpgs-render --video`, through imageio and the ffmpeg binary of the imageio-ffmpeg wheel
(the optional extra `video`).

Frames are encoded as they are rendered (an orbit of large frames need not fit in memory) into a temp file
beside the target, which replaces the target only once ffmpeg has finished: a crash or Ctrl-C leaves no
half-written MP4 (and an older video, if any, intact).
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from warpgs.data.video.decode import VideoUnavailable, require_video_support


def check_video_support() -> None:
    """Raise VideoUnavailable, naming the extra to install, unless MP4s can be written."""
    require_video_support("writing MP4")


class Mp4Writer:
    """`with Mp4Writer(path, fps) as video: video.append(rgb)` for rgb [H, W, 3] floats in [0, 1].

    H.264 in yuv420p (what browsers and players take) needs even sizes, so odd frames get their last row or
    column repeated; frames are never rescaled."""

    def __init__(self, path, fps: float = 30.0):
        if not fps > 0:
            raise ValueError(f"fps: expected a positive number, got {fps}")
        check_video_support()
        self.path, self.fps = Path(path), float(fps)
        self.frames = 0
        self._tmp = self._writer = None

    def __enter__(self) -> "Mp4Writer":
        import imageio.v2 as imageio

        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.path.parent, prefix=f".{self.path.stem}.", suffix=".tmp.mp4")
        os.close(fd)  # ffmpeg opens it by name (the .mp4 suffix picks the container)
        self._tmp = Path(tmp)
        self._writer = imageio.get_writer(self._tmp, format="FFMPEG", mode="I", fps=self.fps, codec="libx264",
                                          pixelformat="yuv420p", macro_block_size=1, ffmpeg_log_level="error")
        return self

    def append(self, rgb) -> None:
        frame = np.clip(np.round(np.asarray(rgb, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)
        if frame.ndim != 3 or frame.shape[2] != 3:
            raise ValueError(f"video frame: expected [H, W, 3], got shape {frame.shape}")
        pad = ((0, frame.shape[0] % 2), (0, frame.shape[1] % 2), (0, 0))
        self._writer.append_data(np.pad(frame, pad, mode="edge") if any(p[1] for p in pad[:2]) else frame)
        self.frames += 1

    def __exit__(self, exc_type, exc, tb) -> bool:
        try:
            self._writer.close()
            if exc_type is None:
                if self.frames == 0:
                    raise ValueError(f"{self.path}: no frames to write")
                os.chmod(self._tmp, 0o644)
                os.replace(self._tmp, self.path)
        finally:
            if self._tmp.exists():
                self._tmp.unlink()
        return False
