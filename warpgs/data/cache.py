"""Where derived files (resized/undistorted images, generated scenes) are cached on disk."""
from __future__ import annotations

import hashlib
import os
import shutil
import sys
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


def publish_folder(folder: Path, entry: Path, what: str = "files") -> None:
    """Copy `folder` into the cache as `entry` through a temporary copy renamed into place, so a run reading the
    cache never sees half an entry; a run that published it first wins. A read-only or full cache only costs the
    next run the time (one line on stderr)."""
    tmp = entry.with_name(f".{entry.name}.{os.getpid()}.tmp")
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(folder, tmp)
        if not entry.exists():
            os.rename(tmp, entry)
    except OSError as exc:
        if not entry.exists():
            print(f"{what}: could not cache them in {entry} ({exc})", file=sys.stderr)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
