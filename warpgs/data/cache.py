"""Where derived files (resized/undistorted images, generated scenes) are cached on disk, and what is there.

Kinds of entry: images/<2 hex>/<key>.png (a resized or undistorted image, with its .alpha.png), depth_priors/<key>/,
triangulation/<key>/, synthetic/<name>/. A read marks its entry as used (touch), so `warpgs-cache --max-gb` drops
the entries used least recently first. Every entry can be made again (a later run redoes the work)."""
from __future__ import annotations

import hashlib
import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence

KINDS = ("images", "depth_priors", "triangulation", "synthetic")


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


def touch(path: Path) -> None:
    """Mark a cache entry (file or folder) as used now; a read-only cache is left as it is."""
    try:
        os.utime(path)
    except OSError:
        pass


@dataclass
class CacheEntry:
    kind: str
    path: Path  # the entry: an image file (with its alpha file beside it) or a folder
    nbytes: int
    used: float  # last use (modification time, renewed by touch), seconds since the epoch


def cache_entries(root: Optional[Path] = None) -> List[CacheEntry]:
    """Every entry of the cache (default cache_dir()), by kind; files being published (.*.tmp) are skipped."""
    root = Path(root) if root is not None else cache_dir()
    out = []
    for kind in KINDS:
        folder = root / kind
        if not folder.is_dir():
            continue
        if kind == "images":
            items = [f for sub in folder.iterdir() if sub.is_dir() for f in sub.iterdir()
                     if f.is_file() and not f.name.endswith(".alpha.png")]
        else:
            items = [d for d in folder.iterdir() if d.is_dir()]
        for item in items:
            if item.name.startswith("."):
                continue
            parts = [item, item.with_suffix(".alpha.png")] if item.is_file() else list(item.rglob("*"))
            size = sum(f.stat().st_size for f in parts if f.is_file())
            out.append(CacheEntry(kind, item, size, item.stat().st_mtime))
    return out


def remove_entries(entries: Sequence[CacheEntry]) -> int:
    """Delete these entries; returns the bytes freed (an entry another process removed first counts 0)."""
    freed = 0
    for e in entries:
        try:
            if e.path.is_dir():
                shutil.rmtree(e.path)
            else:
                e.path.unlink()
                e.path.with_suffix(".alpha.png").unlink(missing_ok=True)
            freed += e.nbytes
        except FileNotFoundError:
            pass
    return freed


def least_recently_used(entries: Sequence[CacheEntry], max_bytes: int) -> List[CacheEntry]:
    """The entries to drop, least recently used first, so that what stays fits in max_bytes."""
    total = sum(e.nbytes for e in entries)
    drop = []
    for e in sorted(entries, key=lambda e: e.used):
        if total <= max_bytes:
            break
        drop.append(e)
        total -= e.nbytes
    return drop

