"""Offline stand-in for CLIP image features, built from per-pixel label maps.

Every label name gets its fixed 512-d unit "text" embedding (`HashTextEncoder`); each labelled object in a view
becomes one segment whose feature is that embedding plus Gaussian noise of norm ~`noise`, re-normalised (as CLIP
features are). Unlabelled pixels (id 0) get no segment. The result is written LangSplat-style (see
`warpgs.language.features_io`), so training reads it exactly as it would read real extracted features.

noise=0.3 gives a cosine of ~0.96 between a segment and its name; 0.75 gives ~0.8, closer to how well real CLIP
crops match across views.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Mapping, Optional, Tuple

import numpy as np

from warpgs.language.features_io import FOLDER, save_view_features, write_feature_meta
from warpgs.language.text import CLIP_DIM, hash_embedding


def standin_view_features(labels: np.ndarray, names: Mapping[int, str], *, noise: float = 0.3,
                          dim: int = CLIP_DIM, rng: Optional[np.random.Generator] = None) -> Tuple[np.ndarray, np.ndarray]:
    """(segments [H, W] int, features [M, dim]) for one label map ([H, W] ints, 0 = unlabelled)."""
    if noise < 0 or not np.isfinite(noise):
        raise ValueError(f"noise: expected a finite number >= 0, got {noise}")
    rng = rng if rng is not None else np.random.default_rng(0)
    labels = np.asarray(labels)
    ids = [int(i) for i in np.unique(labels) if i != 0]
    missing = [i for i in ids if i not in names]
    if missing:
        raise ValueError(f"labels: ids {missing} have no name")
    seg = np.full(labels.shape, -1, np.int64)
    feats = np.zeros((len(ids), dim), np.float32)
    for k, label in enumerate(ids):
        seg[labels == label] = k
        v = hash_embedding(names[label], dim).astype(np.float64)
        v = v + noise * rng.standard_normal(dim) / np.sqrt(dim)
        feats[k] = v / max(np.linalg.norm(v), 1e-12)
    return seg, feats


def _view_seed(seed: int, name: str) -> int:
    return int.from_bytes(hashlib.sha256(f"{seed}\x00{name}".encode()).digest()[:8], "little")


def write_standin_features(scene, out_folder=None, *, noise: float = 0.3, dim: int = CLIP_DIM, seed: int = 0,
                           views=None) -> Path:
    """Write stand-in features for the scene's labelled views into out_folder (default <scene>/language_features).

    Needs label maps and names (labels/<stem>.png + labels.json); views without a label map are skipped.
    Deterministic in (labels, names, noise, dim, seed). Returns the folder.
    """
    if not scene.label_names:
        raise ValueError(f"{scene.root}: no labels.json (label names); the stand-in needs named label maps")
    folder = Path(out_folder) if out_folder is not None else Path(scene.root) / FOLDER
    indices = range(len(scene)) if views is None else views
    written = 0
    for i in indices:
        labels = scene.labels_np(i)
        if labels is None:
            continue
        name = scene.cameras[i].name
        seg, feats = standin_view_features(labels, scene.label_names, noise=noise, dim=dim,
                                           rng=np.random.default_rng(_view_seed(seed, name)))
        save_view_features(folder, name, seg, feats)
        written += 1
    if not written:
        raise ValueError(f"{scene.root}: no view has a label map (labels/<stem>.png)")
    meta = {"source": "standin", "text_encoder": "hash", "dim": dim, "noise": noise, "seed": seed,
            "labels": {str(k): v for k, v in scene.label_names.items()}, "views": written}
    write_feature_meta(folder, meta)
    return folder
