"""Which image pairs to match, so that matching grows with the number of images rather than its square.

Small sets are matched exhaustively. Larger ones are matched by retrieval: a visual-word vocabulary is built from
the set's own SIFT descriptors (COLMAP's vocabulary-tree matcher needs a downloaded tree file, which offline
installs do not have), each image is described by its tf-idf word histogram, and each image is matched with
its most similar ones. When the file-name order looks like a video (each image's most similar images include
its neighbours in name order) a sequential window is added too. With known poses the neighbours come from the
cameras themselves (near centres, similar viewing directions).

Pairs are written as COLMAP's match list (two image names a line) for pycolmap.match_image_pairs.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import torch

EXHAUSTIVE_MAX_IMAGES = 60  # 1770 pairs; above this, retrieval (or pose neighbours)
RETRIEVAL_NEIGHBOURS = 20  # most similar images each image is matched with
SEQUENTIAL_OVERLAP = 10  # window added for video-like ordered sets
VOCABULARY_WORDS = 1024
DESCRIPTORS_PER_IMAGE = 2000


def sequential_pairs(n: int, overlap: int = SEQUENTIAL_OVERLAP) -> set[tuple[int, int]]:
    return {(i, j) for i in range(n) for j in range(i + 1, min(n, i + overlap + 1))}


def nearest_pairs(similarity: np.ndarray, k: int) -> set[tuple[int, int]]:
    """Each image with its k most similar others (the diagonal is ignored)."""
    sim = np.array(similarity, dtype=np.float64)
    n = len(sim)
    np.fill_diagonal(sim, -np.inf)
    k = min(k, n - 1)
    best = np.argsort(-sim, axis=1, kind="stable")[:, :k]
    return {(min(i, int(j)), max(i, int(j))) for i in range(n) for j in best[i]}


def looks_sequential(similarity: np.ndarray, top: int = 5, fraction: float = 0.8) -> bool:
    """True when, for most images, the next one in name order is among its `top` most similar."""
    sim = np.array(similarity, dtype=np.float64)
    n = len(sim)
    if n < 3:
        return True
    np.fill_diagonal(sim, -np.inf)
    best = np.argsort(-sim, axis=1, kind="stable")[:, :top]
    hits = sum(i + 1 in best[i] or i in best[i + 1] for i in range(n - 1))
    return hits >= fraction * (n - 1)


def _kmeans(x: torch.Tensor, k: int, iters: int, gen: torch.Generator) -> torch.Tensor:
    """Spherical k-means (unit vectors, dot-product assignment); returns [k, d] unit centres."""
    centres = x[torch.randperm(len(x), generator=gen)[:k]].clone()
    for _ in range(iters):
        assign = (x @ centres.T).argmax(1)
        sums = torch.zeros_like(centres).index_add_(0, assign, x)
        counts = torch.bincount(assign, minlength=len(centres))
        empty = counts == 0
        if empty.any():  # restart empty words on random descriptors
            sums[empty] = x[torch.randint(len(x), (int(empty.sum()),), generator=gen)]
        centres = torch.nn.functional.normalize(sums, dim=1)
    return centres


def word_similarity(descriptors: Sequence[np.ndarray], words: int = VOCABULARY_WORDS, iters: int = 8,
                    seed: int = 0) -> np.ndarray:
    """[n, n] cosine similarity of the images' tf-idf visual-word histograms (SIFT descriptors, uint8 [m, 128])."""
    gen = torch.Generator().manual_seed(seed)
    # np.asarray(..., float32) copies: descriptors read from the database are read-only buffers torch warns about.
    feats = [torch.nn.functional.normalize(torch.from_numpy(np.asarray(d, dtype=np.float32).reshape(-1, 128)), dim=1)
             for d in descriptors]
    pool = torch.cat([f[torch.randperm(len(f), generator=gen)[:200]] for f in feats if len(f)])
    if len(pool) == 0:
        return np.eye(len(descriptors))
    centres = _kmeans(pool, min(words, len(pool)), iters, gen)
    hist = torch.zeros(len(feats), len(centres))
    for i, f in enumerate(feats):
        if len(f):
            hist[i] = torch.bincount((f @ centres.T).argmax(1), minlength=len(centres)).float()
    df = (hist > 0).sum(0).float()
    idf = torch.log(len(feats) / df.clamp_min(1.0))
    tfidf = torch.nn.functional.normalize(hist / hist.sum(1, keepdim=True).clamp_min(1.0) * idf, dim=1)
    return (tfidf @ tfidf.T).numpy()


def pose_similarity(centres: np.ndarray, forwards: np.ndarray) -> np.ndarray:
    """Similarity of known cameras for picking neighbours: near centres (in units of the median nearest-neighbour
    distance) looking the same way score high; cameras facing apart by more than 90 degrees score lowest."""
    centres, forwards = np.asarray(centres, np.float64), np.asarray(forwards, np.float64)
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    off = dist + np.diag(np.full(len(dist), np.inf))
    scale = max(float(np.median(off.min(1))), 1e-12) if len(dist) > 1 else 1.0
    cos = np.clip(forwards @ forwards.T, -1.0, 1.0)
    return -dist / scale + 4.0 * cos - np.where(cos < 0, 1e6, 0.0)


def read_descriptors(database: Path, max_per_image: int = DESCRIPTORS_PER_IMAGE) -> tuple[list[str], list[np.ndarray]]:
    """(image names, SIFT descriptors) from a COLMAP database, in name order; at most max_per_image each."""
    import pycolmap

    with pycolmap.Database.open(str(database)) as db:
        images = sorted(db.read_all_images(), key=lambda im: im.name)
        descs = []
        for im in images:
            d = np.asarray(db.read_descriptors(im.image_id).data)
            if len(d) > max_per_image:
                d = d[np.linspace(0, len(d) - 1, max_per_image).astype(int)]
            descs.append(d)
    return [im.name for im in images], descs


def write_pairs(path: Path, names: Sequence[str], pairs: Iterable[tuple[int, int]]) -> Path:
    path = Path(path)
    path.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in sorted(pairs)))
    return path
