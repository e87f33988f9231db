"""Structure from motion on image folders (`warpgs.data.run_sfm`): images registered, points, reprojection
error and seconds per stage, for the "SfM that finishes" target (a ~300-photo capture registered >= 95% in
<= 10 minutes on a 16-core machine).

    python benchmarks/sfm.py data/stam464/images [more folders] [--matcher auto] [--threads -1] [--name NAME]
    python benchmarks/sfm.py data/liberty/images --mapper global --reference data/liberty   # poses checked too

Each folder holds the images of one capture (no model). The reconstruction goes to a temporary folder (or
--out/<folder name>); the figures go to benchmarks/results/sfm_<name>.json. The number of cores used is
recorded: COLMAP's features, matching and bundle adjustment run on all of them.

`--reference SCENE` (one folder only): a scene warpgs reads (COLMAP, LLFF, transforms.json) holding the same images
with known poses, e.g. the capture author's own reconstruction. The registered cameras are then aligned to it by a
similarity and compared: a count of registered images cannot tell a right pose from a wrong one.
"""
from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

import numpy as np

from common import ROOT, print_table, write_json

sys.path.insert(0, str(ROOT))

from warpgs.data.extent import camera_radius  # noqa: E402
from warpgs.data.formats.colmap import load_colmap  # noqa: E402
from warpgs.data.formats.image_io import image_size, list_images  # noqa: E402
from warpgs.data.formats.load import load_scene  # noqa: E402
from warpgs.data.sfm.run import pycolmap_threads, run_sfm  # noqa: E402
from warpgs.data.sfm.sim3 import pose_errors  # noqa: E402


def capture_name(folder: Path) -> str:
    """A capture's name: the folder's, or its parent's for a folder called images/."""
    return folder.parent.name if folder.name == "images" else folder.name


def pose_agreement(estimated, reference) -> dict:
    """Registered cameras against reference cameras of the same images (matched by file name), after a similarity
    alignment (rotation from the orientations, scale and shift from the centres): rotation errors in degrees,
    centre errors as a fraction of the reference cameras' spread (the largest distance of a centre from their
    mean), and how many images were compared."""
    ref = {c.name: c for c in reference}
    pairs = [(c, ref[c.name]) for c in estimated if c.name in ref]
    if len(pairs) < 3:
        raise SystemExit(f"--reference: only {len(pairs)} registered images have a reference pose (need 3); "
                         "do the two folders hold the same file names?")
    # Aligned by orientations: a video sweep's centres lie near a line, where aligning the centres is ill-posed.
    errors = pose_errors([e for e, _ in pairs], [r for _, r in pairs], align="orientations")
    spread = camera_radius([r for _, r in pairs])
    rot, ctr = np.asarray(errors["rotation_deg"]), np.asarray(errors["center"]) / max(spread, 1e-12)
    return {"compared": len(pairs), "rotation_deg_median": round(float(np.median(rot)), 3),
            "rotation_deg_max": round(float(rot.max()), 3), "center_median": round(float(np.median(ctr)), 4),
            "center_max": round(float(ctr.max()), 4), "over_5deg": int((rot > 5).sum())}


def reconstruct(folder: Path, out: Path, matcher: str, threads: int, peak_threshold=None,
                mapper: str = "incremental", reference: Optional[Path] = None) -> dict:
    import pycolmap

    images = list_images(folder)
    t0 = time.perf_counter()
    sparse = run_sfm(folder, out, matcher=matcher, num_threads=threads, peak_threshold=peak_threshold, mapper=mapper)
    seconds = time.perf_counter() - t0
    model = pycolmap.Reconstruction(str(sparse))
    models = [p for p in (out / "sparse").iterdir() if p.is_dir()]
    w, h = image_size(images[0])
    row = {"folder": str(folder), "images": len(images), "size": [w, h], "matcher": matcher, "mapper": mapper,
           "peak_threshold": peak_threshold,
           "registered": model.num_reg_images(), "registered_fraction": round(model.num_reg_images() / len(images), 4),
           "models": len(models), "points": model.num_points3D(),
           "error_px": round(model.compute_mean_reprojection_error(), 4), "seconds": round(seconds, 1),
           "stages": {k: round(v, 1) for k, v in run_sfm.last_times.items()}}
    if reference is not None:
        estimated = load_colmap(out, model_dir=sparse, images_dir=folder, split="all", undistort=False).native_cameras
        given = load_scene(reference, split="all", run_sfm_if_needed=False, undistort=False).native_cameras
        row["poses_vs_reference"] = {"reference": str(reference), **pose_agreement(estimated, given)}
    return row


def main(argv=None) -> list:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+", help="image folders, one capture each")
    ap.add_argument("--matcher", default="auto", help="auto | exhaustive | sequential | retrieval")
    ap.add_argument("--mapper", default="incremental", help="incremental | global (GLOMAP)")
    ap.add_argument("--threads", type=int, default=-1, help="-1: every core")
    ap.add_argument("--peak-threshold", type=float, default=None, help="SIFT threshold (default: run_sfm's choice)")
    ap.add_argument("--out", default=None, help="keep the reconstructions under this folder")
    ap.add_argument("--name", default=None, help="result file suffix (default: the first folder's name)")
    ap.add_argument("--reference", default=None, help="a scene folder with the same images' known poses: compare")
    args = ap.parse_args(argv)
    if args.reference is not None and (len(args.folders) != 1 or not Path(args.reference).is_dir()):
        raise SystemExit(f"--reference {args.reference}: needs one image folder and an existing scene folder")
    for f in args.folders:
        if not Path(f).is_dir():
            raise SystemExit(f"{f}: not a folder of images")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(args.out or tmp)
        for f in map(Path, args.folders):
            rows.append(reconstruct(f, base / capture_name(f), args.matcher, args.threads, args.peak_threshold,
                                    args.mapper, Path(args.reference) if args.reference else None))
            print_table([rows[-1]], ["images", "registered", "models", "points", "error_px", "seconds"])
            if "poses_vs_reference" in rows[-1]:
                print("poses against the reference:", rows[-1]["poses_vs_reference"])
    payload = {"runs": rows, "cores": pycolmap_threads() if args.threads < 1 else args.threads,
               "machine": platform.processor() or platform.machine(), "command": " ".join(sys.argv)}
    print(f"wrote {write_json('sfm_' + (args.name or capture_name(Path(args.folders[0]))), payload)}")
    return rows


if __name__ == "__main__":
    main()
