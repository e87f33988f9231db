"""PNG helpers for query results: a heat colour map, relevancy overlays and mask tints (numpy + Pillow)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

# Anchor colours of a blue -> cyan -> green -> yellow -> red map, evenly spaced on [0, 1].
_ANCHORS = np.array([[0.19, 0.07, 0.55], [0.12, 0.55, 0.90], [0.20, 0.80, 0.45], [0.95, 0.85, 0.15],
                     [0.85, 0.10, 0.08]], np.float32)


def heat_colors(values: np.ndarray) -> np.ndarray:
    """[...] values in [0, 1] -> [..., 3] RGB in [0, 1]."""
    v = np.clip(np.nan_to_num(np.asarray(values, np.float32)), 0.0, 1.0) * (len(_ANCHORS) - 1)
    lo = np.floor(v).astype(np.int64).clip(0, len(_ANCHORS) - 2)
    t = (v - lo)[..., None]
    return _ANCHORS[lo] * (1 - t) + _ANCHORS[lo + 1] * t


def relevancy_overlay(rgb: np.ndarray, relevancy: np.ndarray, strength: float = 0.7) -> np.ndarray:
    """Heat colours blended over the render in proportion to the (normalised) relevancy."""
    a = (strength * np.clip(relevancy, 0, 1))[..., None]
    return np.clip(rgb, 0, 1) * (1 - a) + heat_colors(relevancy) * a


def mask_overlay(rgb: np.ndarray, mask: np.ndarray, color=(1.0, 0.1, 0.1), strength: float = 0.55) -> np.ndarray:
    """Tint the masked pixels and draw their outline."""
    out = np.clip(rgb, 0, 1).copy()
    m = np.asarray(mask, bool)
    out[m] = out[m] * (1 - strength) + np.asarray(color, np.float32) * strength
    edge = m & ~_erode(m)
    out[edge] = color
    return out


def _erode(mask: np.ndarray) -> np.ndarray:
    m = np.pad(mask, 1, constant_values=False)
    return (m[1:-1, 1:-1] & m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:])


def save_png(path, array: np.ndarray) -> Path:
    from warpgs.data.formats.image_io import write_png

    return write_png(Path(path), np.asarray(array))
