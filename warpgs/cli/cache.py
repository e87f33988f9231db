"""`warpgs-cache [--clear [KIND ...]] [--max-gb G]`: what the derived-file cache holds ($WARPGS_CACHE, else
~/.cache/warpgs: resized images, depth priors, triangulated points, generated scenes), and freeing it. Every entry
is made again by the next run that needs it; do not clear entries while a run is reading them."""
from __future__ import annotations

import argparse
import time
from typing import List, Optional

from warpgs.cli.common import EXIT_CONFIG, report_error
from warpgs.data.cache import KINDS, cache_dir, cache_entries, least_recently_used, remove_entries

PROG = "warpgs-cache"
GB = 1e9


def _summary(entries) -> str:
    lines = []
    for kind in KINDS:
        mine = [e for e in entries if e.kind == kind]
        if mine:
            newest = max(e.used for e in mine)
            lines.append(f"  {kind:<14} {len(mine):6d} entries {sum(e.nbytes for e in mine) / GB:9.3f} GB  "
                         f"last used {_ago(time.time() - newest)} ago")
    lines.append(f"  {'total':<14} {len(entries):6d} entries {sum(e.nbytes for e in entries) / GB:9.3f} GB")
    return "\n".join(lines)


def _ago(seconds: float) -> str:
    return f"{seconds / 86400:.0f} d" if seconds >= 86400 else f"{max(seconds, 0) / 3600:.1f} h"


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(
        prog=PROG, description="What the derived-file cache holds (resized images, depth priors, triangulated "
                               "points, generated scenes), and freeing it. Every entry is made again by the next "
                               "run that needs it; do not clear entries while a run is reading them.")
    ap.add_argument("--clear", nargs="*", metavar="KIND",
                    help=f"delete every entry, or those of the kinds named ({', '.join(KINDS)})")
    ap.add_argument("--max-gb", type=float, metavar="G",
                    help="delete the least recently used entries until the cache holds at most G GB")
    args = ap.parse_args(argv)
    if args.clear is not None and args.max_gb is not None:
        return report_error(PROG, "--clear and --max-gb: give one of them", EXIT_CONFIG)
    unknown = [k for k in args.clear or () if k not in KINDS]
    if unknown:
        return report_error(PROG, f"--clear: unknown kind {', '.join(unknown)} (kinds: {', '.join(KINDS)})",
                            EXIT_CONFIG)
    if args.max_gb is not None and not args.max_gb >= 0:
        return report_error(PROG, f"--max-gb: expected a size in GB >= 0, got {args.max_gb}", EXIT_CONFIG)
    root = cache_dir()
    entries = cache_entries(root)
    print(f"cache: {root}" + ("" if root.is_dir() else " (not created yet)"))
    if args.clear is not None:
        kinds = set(args.clear or KINDS)
        drop = [e for e in entries if e.kind in kinds]
    elif args.max_gb is not None:
        drop = least_recently_used(entries, int(args.max_gb * GB))
    else:
        print(_summary(entries))
        return 0
    freed = remove_entries(drop)
    print(f"deleted {len(drop)} entries, {freed / GB:.3f} GB")
    print(_summary(cache_entries(root)))
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main())
