"""Shared helpers for the data tests: synthetic scenes rendered once per test process, small image writers."""
from __future__ import annotations

import atexit
import functools
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

from warpgs.data.formats.synthetic import default_scene, write_synthetic_scene

_ROOT = Path(tempfile.mkdtemp(prefix="warpgs-data-tests-"))
atexit.register(shutil.rmtree, _ROOT, ignore_errors=True)
GENERATION_SECONDS: dict = {}


@functools.lru_cache(maxsize=None)
def synthetic_dir(kind: str) -> Path:
    """The synthetic scene of this kind at 128x96, rendered on first use (tests must not modify it)."""
    start = time.perf_counter()
    path = write_synthetic_scene(_ROOT / kind, kind)
    GENERATION_SECONDS[kind] = time.perf_counter() - start
    return path


@functools.lru_cache(maxsize=None)
def default_lightfield() -> tuple[Path, float, Path]:
    """default_scene() generated into a private cache: (scene folder, seconds it took, the cache folder)."""
    cache = _ROOT / "cache"
    previous = os.environ.get("WARPGS_CACHE")
    os.environ["WARPGS_CACHE"] = str(cache)
    try:
        start = time.perf_counter()
        path = default_scene()
        return path, time.perf_counter() - start, cache
    finally:
        if previous is None:
            del os.environ["WARPGS_CACHE"]
        else:
            os.environ["WARPGS_CACHE"] = previous


def copy_of(kind: str, dest: Path) -> Path:
    """A private, modifiable copy of a synthetic scene folder."""
    return Path(shutil.copytree(synthetic_dir(kind), dest))


def write_rgb(path: Path, width: int, height: int, seed: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    rgb = np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(path)
    return path
