"""Do a video capture's poses move smoothly? Consecutive frames of a video are a few degrees and a short step apart;
a pose that turns half around between two frames that look alike was put on the wrong side of the scene by SfM
(a symmetric object, repeated texture). Such frames train against the others and make held-out scores erratic.

    python benchmarks/pose_continuity.py data/beer [--format colmap] [--name NAME]

Frames are taken in natural name order (frame_2 before frame_10). Prints the median step and every jump: a step
turning more than --max-turn degrees, or moving more than --max-step times the median distance; when every jump
is a half turn, the two halves of the folded orbit (warpgs.data.pose_checks.folded_halves). Writes
benchmarks/results/pose_continuity_<name>.json. Meaningful for video frames only, not for photo collections."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from common import ROOT, print_table, write_json

sys.path.insert(0, str(ROOT))

from warpgs.data.formats.load import load_scene  # noqa: E402
from warpgs.data.pose_checks import continuity, folded_halves, side_ranges  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", help="scene folder with poses (COLMAP, LLFF, transforms.json)")
    ap.add_argument("--format", default=None, help="the loader to use where a folder has several (e.g. colmap)")
    ap.add_argument("--max-turn", type=float, default=60.0, help="a jump turns more than this many degrees")
    ap.add_argument("--max-step", type=float, default=5.0, help="or moves more than this many median steps")
    ap.add_argument("--name", default=None, help="result file suffix (default: the folder's name)")
    args = ap.parse_args(argv)
    if not Path(args.data).is_dir():
        raise SystemExit(f"data: {args.data} is not a folder")
    scene = load_scene(args.data, split="all", run_sfm_if_needed=False, undistort=False, format=args.format)
    try:
        found = continuity(scene.native_cameras, args.max_turn, args.max_step)
    except ValueError as e:
        raise SystemExit(f"{args.data}: {e}")
    print(f"{found['frames']} frames, median step {found['median_turn_deg']} deg / {found['median_step']:.4g} units")
    if found["jumps"]:
        print_table(found["jumps"], ["from", "to", "turn_deg", "step_over_median"])
    else:
        print("no jumps")
    found["folded_halves"] = folded_halves(scene.native_cameras, found["jumps"])  # the jumps printed above
    for k, side in enumerate(found["folded_halves"]):
        ranges, frames = side_ranges(side)
        print(f"half {k + 1}: {ranges} ({frames} frames)")
    found.update(data=str(args.data), format=args.format, command=" ".join(sys.argv))
    print(f"wrote {write_json('pose_continuity_' + (args.name or Path(args.data).name), found)}")
    return found


if __name__ == "__main__":
    main()
