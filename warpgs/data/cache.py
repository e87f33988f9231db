"""Where derived files (resized/undistorted images, generated scenes) are cached on disk."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path


def cache_dir() -> Path:
    """$WARPGS_CACHE, else $XDG_CACHE_HOME/warpgs, else ~/.cache/warpgs."""
    if os.environ.get("WARPGS_CACHE"):
        return Path(os.environ["WARPGS_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "warpgs"


def file_key(path: Path, *extra) -> str:
    """A key that changes whenever the file is replaced or edited, or when `extra` (settings) changes."""
    stat = Path(path).stat()
    text = "|".join([str(Path(path).resolve()), str(stat.st_mtime_ns), str(stat.st_size), *map(str, extra)])
    return hashlib.sha1(text.encode()).hexdigest()[:20]
