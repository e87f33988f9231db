"""Structure from motion on image folders (`warpgs.data.sfm.run_sfm`): images registered, points, reprojection
error and seconds per stage, for the "SfM that finishes" target (a ~300-photo capture registered >= 95% in
<= 10 minutes on a 16-core machine).

    python benchmarks/sfm.py data/stam464/images [more folders] [--matcher auto] [--threads -1] [--name NAME]

Each folder holds the images of one capture (no model). The reconstruction goes to a temporary folder (or
--out/<folder name>); the figures go to benchmarks/results/sfm_<name>.json. The number of cores used is
recorded: COLMAP's features, matching and bundle adjustment run on all of them.
"""
from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

from common import ROOT, print_table, write_json

sys.path.insert(0, str(ROOT))

from warpgs.data.formats.image_io import image_size, list_images  # noqa: E402
from warpgs.data.sfm.run import pycolmap_threads, run_sfm  # noqa: E402


def capture_name(folder: Path) -> str:
    """A capture's name: the folder's, or its parent's for a folder called images/."""
    return folder.parent.name if folder.name == "images" else folder.name


def reconstruct(folder: Path, out: Path, matcher: str, threads: int, peak_threshold=None,
                mapper: str = "incremental") -> dict:
    import pycolmap

    images = list_images(folder)
    t0 = time.perf_counter()
    sparse = run_sfm(folder, out, matcher=matcher, num_threads=threads, peak_threshold=peak_threshold, mapper=mapper)
    seconds = time.perf_counter() - t0
    model = pycolmap.Reconstruction(str(sparse))
    models = [p for p in (out / "sparse").iterdir() if p.is_dir()]
    w, h = image_size(images[0])
    return {"folder": str(folder), "images": len(images), "size": [w, h], "matcher": matcher, "mapper": mapper,
            "peak_threshold": peak_threshold,
            "registered": model.num_reg_images(), "registered_fraction": round(model.num_reg_images() / len(images), 4),
            "models": len(models), "points": model.num_points3D(),
            "error_px": round(model.compute_mean_reprojection_error(), 4), "seconds": round(seconds, 1),
            "stages": {k: round(v, 1) for k, v in run_sfm.last_times.items()}}


def main(argv=None) -> list:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folders", nargs="+", help="image folders, one capture each")
    ap.add_argument("--matcher", default="auto", help="auto | exhaustive | sequential | retrieval")
    ap.add_argument("--mapper", default="incremental", help="incremental | global (GLOMAP)")
    ap.add_argument("--threads", type=int, default=-1, help="-1: every core")
    ap.add_argument("--peak-threshold", type=float, default=None, help="SIFT threshold (default: run_sfm's choice)")
    ap.add_argument("--out", default=None, help="keep the reconstructions under this folder")
    ap.add_argument("--name", default=None, help="result file suffix (default: the first folder's name)")
    args = ap.parse_args(argv)
    for f in args.folders:
        if not Path(f).is_dir():
            raise SystemExit(f"{f}: not a folder of images")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(args.out or tmp)
        for f in map(Path, args.folders):
            rows.append(reconstruct(f, base / capture_name(f), args.matcher, args.threads, args.peak_threshold,
                                    args.mapper))
            print_table([rows[-1]], ["images", "registered", "models", "points", "error_px", "seconds"])
    payload = {"runs": rows, "cores": pycolmap_threads() if args.threads < 1 else args.threads,
               "machine": platform.processor() or platform.machine(), "command": " ".join(sys.argv)}
    print(f"wrote {write_json('sfm_' + (args.name or capture_name(Path(args.folders[0]))), payload)}")
    return rows


if __name__ == "__main__":
    main()
