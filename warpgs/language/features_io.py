"""Per-view language features stored LangSplat-style, one pair of .npy files per image:

    <folder>/<stem>_s.npy   segment map, int [H, W] or [L, H, W] (L levels, e.g. LangSplat's default/s/m/l);
                            each value indexes a row of _f.npy, -1 = no segment
    <folder>/<stem>_f.npy   features, float [M, C] (C = 512 for CLIP ViT-B/16), one per segment

    <folder>/features.json  what made the folder (source, text_encoder, dim, ...), written by the extractors

The folder is `<scene>/language_features` by default. Only one level is used (PPGS uses the "whole object"
level); `level` picks it (0 for single-level maps and for LangSplat's "default" plane).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable, Optional, Tuple

import numpy as np

from warpgs.utils.atomic_file import atomic_write_bytes

FOLDER = "language_features"
SEG_SUFFIX = "_s.npy"
FEAT_SUFFIX = "_f.npy"
META_FILE = "features.json"


class FeatureFileError(ValueError):
    """A missing or malformed language-feature file; the message names the file."""


def feature_paths(folder, image_name: str) -> Tuple[Path, Path]:
    stem = Path(image_name).stem
    folder = Path(folder)
    return folder / f"{stem}{SEG_SUFFIX}", folder / f"{stem}{FEAT_SUFFIX}"


def write_feature_meta(folder, meta: dict) -> None:
    """Record what made the folder's features (its features.json)."""
    atomic_write_bytes(Path(folder) / META_FILE, json.dumps(meta, indent=1).encode())


def read_feature_meta(folder) -> dict:
    """The folder's features.json ({} when absent or unreadable): source, text_encoder, dim, ..."""
    path = Path(folder) / META_FILE
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError:
        return {}


def has_view_features(folder, image_name: str) -> bool:
    seg, feat = feature_paths(folder, image_name)
    return seg.is_file() and feat.is_file()


def save_view_features(folder, image_name: str, segments: np.ndarray, features: np.ndarray) -> Tuple[Path, Path]:
    """Write one view's segment map ([H,W] or [L,H,W] ints, -1 = none) and its [M, C] features."""
    segments = np.asarray(segments)
    features = np.asarray(features, dtype=np.float32)
    if segments.ndim not in (2, 3) or not np.issubdtype(segments.dtype, np.integer):
        raise ValueError(f"segments: expected an integer [H, W] or [L, H, W] array, got {segments.dtype} {segments.shape}")
    if features.ndim != 2:
        raise ValueError(f"features: expected [M, C], got shape {features.shape}")
    if segments.size and (segments.min() < -1 or segments.max() >= len(features)):
        raise ValueError(f"segments: values must lie in [-1, {len(features) - 1}]")
    if not np.all(np.isfinite(features)):
        raise ValueError("features: contain NaN or Inf")
    seg_path, feat_path = feature_paths(folder, image_name)
    seg_path.parent.mkdir(parents=True, exist_ok=True)
    dtype = np.int16 if len(features) < np.iinfo(np.int16).max else np.int32
    np.save(seg_path, segments.astype(dtype))
    np.save(feat_path, features)
    return seg_path, feat_path


def load_view_features(folder, image_name: str, level: int = 0) -> Tuple[np.ndarray, np.ndarray]:
    """(segments [H, W] int64 with -1 = none, features [M, C] float32) of one view at `level`."""
    seg_path, feat_path = feature_paths(folder, image_name)
    for p in (seg_path, feat_path):
        if not p.is_file():
            raise FeatureFileError(f"{p}: language feature file not found")
    try:
        seg = np.load(seg_path, allow_pickle=False)
        feat = np.load(feat_path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise FeatureFileError(f"{seg_path.parent}/{Path(image_name).stem}_*.npy: unreadable ({exc})") from exc
    if seg.ndim == 3:
        if not 0 <= level < seg.shape[0]:
            raise FeatureFileError(f"{seg_path}: level {level} requested but the map has {seg.shape[0]} levels")
        seg = seg[level]
    elif seg.ndim != 2:
        raise FeatureFileError(f"{seg_path}: expected [H, W] or [L, H, W], got shape {seg.shape}")
    if not np.issubdtype(seg.dtype, np.integer):
        if not np.all(np.equal(np.mod(seg, 1), 0)):
            raise FeatureFileError(f"{seg_path}: segment ids must be integers")
    seg = seg.astype(np.int64)
    if feat.ndim != 2:
        raise FeatureFileError(f"{feat_path}: expected [M, C], got shape {feat.shape}")
    feat = feat.astype(np.float32)
    if not np.all(np.isfinite(feat)):
        raise FeatureFileError(f"{feat_path}: contains NaN or Inf")
    seg = np.where(seg < 0, -1, seg)
    if seg.size and seg.max() >= len(feat):
        raise FeatureFileError(f"{seg_path}: segment id {int(seg.max())} but {feat_path.name} has {len(feat)} rows")
    return seg, feat


def resize_segments(segments: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize of a segment map to [height, width] (pixel centres)."""
    h, w = segments.shape
    if (w, h) == (width, height):
        return segments
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return segments[rows[:, None], cols[None, :]]


def collect_features(folder, image_names: Iterable[str], level: int = 0,
                     weighted: bool = False) -> np.ndarray:
    """All segment features of these views stacked [sum M, C] (only segments that appear in their map).

    weighted=True repeats each feature in proportion to its pixel area (at most 16 copies), approximating
    LangSplat's per-pixel autoencoder training set without storing every pixel.
    """
    rows = []
    for name in image_names:
        seg, feat = load_view_features(folder, name, level)
        ids, counts = np.unique(seg[seg >= 0], return_counts=True)
        if not len(ids):
            continue
        if weighted:
            reps = np.clip(np.round(16 * counts / counts.max()), 1, 16).astype(np.int64)
            rows.append(np.repeat(feat[ids], reps, axis=0))
        else:
            rows.append(feat[ids])
    if not rows:
        raise FeatureFileError(f"{folder}: no segment features found for the given views")
    return np.concatenate(rows, 0)


def find_feature_folder(scene_root, folder: Optional[str] = None) -> Optional[Path]:
    """The scene's LangSplat feature folder (`folder` relative to the scene, default language_features), if any."""
    path = Path(folder) if folder else Path(FOLDER)
    if not path.is_absolute():
        path = Path(scene_root) / path
    return path if path.is_dir() else None
