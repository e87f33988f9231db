"""A rectified light field of the Stanford (New) Light Field Archive as a warpgs light-field folder.

    python benchmarks/stanford_lightfield.py SRC OUT [--rows 5-11 --cols 5-11]

SRC holds the archive's rectified views, named out_RR_CC_<Y>_<X>_.png (grid row and column, then the parallax that
Stanford measured for the view, "related to the centre of projection by an unknown scale and translation"). OUT gets
images/ (hard links, or copies across file systems) and lightfield.json: each view's grid position, its centre on the
array's plane from the measured parallax (so the gantry's ~10% jitter is kept, not rounded to the grid), and
"reference_depth", since every view was warped so that one plane has no parallax.

What the archive leaves unknown, and what is chosen here: the focal length (--focal, default the image width) and
the scale of the centres. For cameras that only translate in one plane, a reconstruction is the same up to a
projective map of space for any choice of these, and every view of the array renders alike; the scale is set so
that a point at infinity moves --infinity-shift pixels (default 10) between neighbouring views, against the
reference plane's 0, which puts that plane at depth 1 and everything nearer than infinity in front of the cameras.
Row indices grow as the camera moves up and X as it moves right (checked on "chess" by image correlation); the
centres use +x right, +y down.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import sys
from pathlib import Path

import numpy as np

NAME = re.compile(r"^out_(\d+)_(\d+)_(-?\d+(?:\.\d+)?)_(-?\d+(?:\.\d+)?)_?\.(png|jpg|jpeg)$", re.IGNORECASE)


def parse_views(names) -> dict[str, tuple[int, int, float, float]]:
    """{file name: (row, col, Y, X)} of the names in Stanford's pattern (the others are left out)."""
    out = {}
    for n in names:
        m = NAME.match(n)
        if m:
            out[n] = (int(m.group(1)), int(m.group(2)), float(m.group(3)), float(m.group(4)))
    return out


def parse_range(text: str | None) -> range | None:
    if not text:
        return None
    lo, _, hi = text.partition("-")
    if not (lo.isdigit() and (hi.isdigit() or not hi)):
        raise SystemExit(f"expected a range such as 5-11, got {text!r}")
    return range(int(lo), int(hi or lo) + 1)


def array_spec(views: dict, width: int, height: int, focal: float | None = None,
               infinity_shift: float = 10.0) -> dict:
    """lightfield.json for these views: grid positions relative to the first row and column, centres from the
    parallax (the middle view at the origin), intrinsics and the reference plane's depth (1)."""
    rows = sorted({v[0] for v in views.values()})
    cols = sorted({v[1] for v in views.values()})
    if len(rows) < 2 or len(cols) < 2:
        raise ValueError(f"a light field needs at least 2 rows and 2 columns of views, got {len(rows)}x{len(cols)}")
    focal = float(focal or width)
    by_pos = {(r, c): (y, x) for r, c, y, x in views.values()}
    # The median parallax between horizontal neighbours: one view step.
    steps = [abs(by_pos[(r, c + 1)][1] - by_pos[(r, c)][1]) for r, c in by_pos if (r, c + 1) in by_pos]
    step = float(np.median(steps))
    if not step > 0:
        raise ValueError("the views' parallax does not change along a row: not a rectified array")
    scale = infinity_shift / (focal * step)  # centre units per parallax unit, with the reference depth at 1
    middle = ((rows[0] + rows[-1]) / 2, (cols[0] + cols[-1]) / 2)
    mid = min(views.values(), key=lambda v: (abs(v[0] - middle[0]), abs(v[1] - middle[1])))
    centres = {n: [scale * (x - mid[3]), scale * (y - mid[2])] for n, (r, c, y, x) in views.items()}
    return {"rows": len(rows), "cols": len(cols),
            "views": {n: [r - rows[0], c - cols[0]] for n, (r, c, _, _) in sorted(views.items())},
            "centres": dict(sorted(centres.items())),
            "intrinsics": {"fx": focal, "fy": focal, "cx": width / 2.0, "cy": height / 2.0},
            "reference_depth": 1.0,
            "source": "Stanford Light Field Archive, rectified (benchmarks/stanford_lightfield.py)"}


def link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", type=Path, help="folder of out_RR_CC_<Y>_<X>_.png views")
    ap.add_argument("out", type=Path, help="the light-field folder to write (images/ and lightfield.json)")
    ap.add_argument("--rows", help="grid rows to keep, e.g. 5-11 (default: all)")
    ap.add_argument("--cols", help="grid columns to keep (default: all)")
    ap.add_argument("--focal", type=float, default=None, help="focal length in pixels (default: the image width)")
    ap.add_argument("--infinity-shift", type=float, default=10.0,
                    help="pixels a point at infinity moves between neighbouring views (sets the centres' scale)")
    args = ap.parse_args(argv)
    if not args.src.is_dir():
        raise SystemExit(f"{args.src}: not a folder")
    views = parse_views(sorted(p.name for p in args.src.iterdir()))
    rows, cols = parse_range(args.rows), parse_range(args.cols)
    views = {n: v for n, v in views.items() if (rows is None or v[0] in rows) and (cols is None or v[1] in cols)}
    if not views:
        raise SystemExit(f"{args.src}: no views named out_RR_CC_<Y>_<X>_.png (in the rows and columns asked for)")
    from warpgs.data.formats.image_io import image_size

    sizes = {tuple(image_size(args.src / n)) for n in views}
    if len(sizes) != 1:
        raise SystemExit(f"{args.src}: the views differ in size: {sorted(sizes)}")
    (width, height), = sizes
    try:
        spec = array_spec(views, width, height, args.focal, args.infinity_shift)
    except ValueError as exc:
        raise SystemExit(f"{args.src}: {exc}")
    (args.out / "images").mkdir(parents=True, exist_ok=True)
    for n in views:
        dst = args.out / "images" / n
        if not dst.exists():
            link_or_copy(args.src / n, dst)
    tmp = args.out / "lightfield.json.tmp"
    tmp.write_text(json.dumps(spec, indent=1))
    tmp.replace(args.out / "lightfield.json")
    print(f"wrote {args.out}: {len(views)} views, {spec['rows']}x{spec['cols']}, {width}x{height}", file=sys.stderr)


if __name__ == "__main__":
    main()
