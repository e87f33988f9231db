"""Text encoders: phrase -> unit embedding in the feature space the scene's language features live in.

`HashTextEncoder` is the offline stand-in for CLIP's text tower: every phrase maps to a fixed random unit
vector seeded by a SHA-256 of its normalised text (lower case, single spaces), so it is the same in every
process and on every machine (Python's salted `hash()` is not). Distinct phrases are nearly orthogonal
(cosine ~ N(0, 1/dim)), which is what a label-derived stand-in needs: the scene's "image" features are these
same vectors plus noise (see `warpgs.language.standin`).

`ClipTextEncoder` (in `warpgs.language.clip`) has the same interface for real CLIP weights.
"""
from __future__ import annotations

import hashlib
from typing import Iterable, Sequence, Union

import numpy as np
import torch

CLIP_DIM = 512
CANONICAL_NEGATIVES = ("object", "things", "stuff", "texture")  # LERF / LangSplat canonical phrases


def normalise_phrase(text: str) -> str:
    if not isinstance(text, str):
        raise ValueError(f"text: expected a string, got {type(text).__name__}")
    phrase = " ".join(text.strip().lower().split())
    if not phrase:
        raise ValueError("text: empty phrase")
    return phrase


def phrase_seed(text: str, namespace: str = "warpgs-text") -> int:
    """A 64-bit seed that depends only on the normalised phrase (stable across processes and platforms)."""
    digest = hashlib.sha256(f"{namespace}\x00{normalise_phrase(text)}".encode("utf-8")).digest()
    return int.from_bytes(digest[:8], "little")


def hash_embedding(text: str, dim: int = CLIP_DIM) -> np.ndarray:
    """[dim] float32 unit vector, deterministic from the phrase."""
    if int(dim) != dim or dim < 2:
        raise ValueError(f"dim: expected an integer >= 2, got {dim}")
    v = np.random.default_rng(phrase_seed(text)).standard_normal(int(dim))
    return (v / np.linalg.norm(v)).astype(np.float32)


class HashTextEncoder:
    """Offline stand-in for a CLIP text encoder (see the module docstring)."""

    name = "hash"

    def __init__(self, dim: int = CLIP_DIM):
        self.dim = int(dim)

    def encode(self, texts: Union[str, Iterable[str]]) -> torch.Tensor:
        """[n, dim] float32 unit rows (one per phrase)."""
        items: Sequence[str] = [texts] if isinstance(texts, str) else list(texts)
        if not items:
            return torch.zeros(0, self.dim)
        return torch.from_numpy(np.stack([hash_embedding(t, self.dim) for t in items]))

    def __repr__(self) -> str:
        return f"HashTextEncoder(dim={self.dim})"


def build_text_encoder(kind: str = "hash", dim: int = CLIP_DIM, **clip_options):
    """"hash" -> HashTextEncoder(dim); "clip" -> ClipTextEncoder(**clip_options) (needs warpgs[clip] + local weights)."""
    if kind == "hash":
        return HashTextEncoder(dim)
    if kind == "clip":
        from warpgs.language.clip import ClipTextEncoder

        return ClipTextEncoder(**clip_options)
    raise ValueError(f"text_encoder: expected 'hash' or 'clip', got {kind!r}")
