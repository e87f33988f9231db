"""Which frames of a video to keep: evenly spaced, and in each stretch the sharpest.

The video's frames are cut into `target` equal windows of consecutive frames; each window gives its sharpest
frame, unless even that one is blurred, in which case the window gives none. Sharpness is the variance of the
Laplacian of the grey frame (high for crisp edges, low under motion or focus blur); "blurred" is relative to the
video itself (below `blur_ratio` times its 90th percentile), as the absolute value depends on the content.
A video blurred from end to end therefore passes; one whose shaky stretches are blurred loses those.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Sequence

import numpy as np

SHARPNESS_SIDE = 640  # frames are scored at about this longest side: fast, and blur of a few pixels still shows
DEFAULT_BLUR_RATIO = 0.35
MIN_SHARP_FRAMES = 10  # fewer than this and SfM has too little to work with


class TooFewSharpFrames(ValueError):
    """The video gave fewer sharp frames than SfM needs."""


def _grey(frame: np.ndarray, max_side: int) -> np.ndarray:
    """Float grey image, block-averaged down by an integer factor so its longest side is about max_side."""
    img = np.asarray(frame, dtype=np.float32)
    grey = img @ np.array([0.299, 0.587, 0.114], np.float32) if img.ndim == 3 else img
    f = max(1, int(np.ceil(max(grey.shape) / max_side)))
    if f > 1:
        h, w = grey.shape[0] // f * f, grey.shape[1] // f * f
        grey = grey[:h, :w].reshape(h // f, f, w // f, f).mean(axis=(1, 3))
    return grey


def sharpness(frame: np.ndarray, max_side: int = SHARPNESS_SIDE) -> float:
    """Variance of the 4-neighbour Laplacian of the grey frame ([H, W, 3] or [H, W], any numeric type)."""
    g = _grey(frame, max_side)
    if min(g.shape) < 3:
        return 0.0
    lap = 4.0 * g[1:-1, 1:-1] - g[:-2, 1:-1] - g[2:, 1:-1] - g[1:-1, :-2] - g[1:-1, 2:]
    return float(lap.var())


def check_selection(target: int, blur_ratio: float, min_frames: int = MIN_SHARP_FRAMES) -> None:
    """ValueError naming the setting when select_frames could never succeed with it (callers check before
    decoding a whole video)."""
    if target < max(1, min_frames):
        raise ValueError(f"frames: expected at least {max(1, min_frames)} (fewer leave SfM too little to work "
                         f"with), got {target}")
    if not 0 <= blur_ratio < 1:
        raise ValueError(f"blur_ratio: expected a value in [0, 1), got {blur_ratio}")


@dataclass
class FrameSelection:
    indices: List[int]  # frames kept, in video order
    total: int  # frames in the video
    windows: int  # spacing windows (the target, or every frame of a shorter video)
    blurred_windows: int  # windows that held only blurred frames and gave none
    threshold: float  # sharpness below this counts as blurred


def select_frames(scores: Sequence[float], target: int, *, blur_ratio: float = DEFAULT_BLUR_RATIO,
                  min_frames: int = MIN_SHARP_FRAMES, source: str = "video") -> FrameSelection:
    """Choose up to `target` frames from per-frame sharpness `scores` (see the module doc). Raises
    TooFewSharpFrames, naming `source`, when fewer than `min_frames` remain."""
    scores = np.asarray(scores, dtype=np.float64)
    check_selection(target, blur_ratio, min_frames)
    n = len(scores)
    windows = min(int(target), n)
    if n == 0:
        raise TooFewSharpFrames(f"{source}: no frames")
    threshold = blur_ratio * float(np.percentile(scores, 90))
    edges = np.linspace(0, n, windows + 1).round().astype(int)
    kept = []
    for a, b in zip(edges[:-1], edges[1:]):
        best = int(a + np.argmax(scores[a:b]))
        if scores[best] >= threshold and scores[best] > 0:
            kept.append(best)
    selection = FrameSelection(kept, n, windows, windows - len(kept), threshold)
    if len(kept) < min_frames:
        raise TooFewSharpFrames(
            f"{source}: only {len(kept)} sharp frame(s) of {n} (need at least {min_frames}); "
            f"{selection.blurred_windows} of {windows} stretches held only blurred frames (sharpness below "
            f"{blur_ratio:g} x the video's 90th percentile). Film longer, more slowly or in more light"
            + (", or lower the blur ratio" if blur_ratio > 0 else ""))
    return selection
