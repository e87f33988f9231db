"""`warpgs-process VIDEO [--out DIR] [--frames N]`: a video to a scene folder (frames + COLMAP model), the step
`warpgs-train --data VIDEO` runs first (warpgs/data/video)."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import List, Optional

from warpgs.cli.common import EXIT_CONFIG, report_error
from warpgs.data.video.scene import DEFAULT_FRAMES, DEFAULT_MAX_SIZE, video_scene_dir
from warpgs.data.video.sharpness import DEFAULT_BLUR_RATIO, MIN_SHARP_FRAMES

PROG = "warpgs-process"


def scene_from_video(video, out=None, *, progress: bool = True, **options) -> Path:
    """video_to_scene with the errors a user can cause turned into ValueError / FileNotFoundError, each naming
    the video, the folder or the extra to install."""
    from warpgs.data.video import VideoUnavailable, video_to_scene

    try:
        return video_to_scene(video, out, progress=progress, **options)
    except VideoUnavailable as e:
        raise ValueError(str(e)) from e


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(
        prog=PROG, description="Turn a video into a scene folder for warpgs-train: evenly spaced frames, the "
                               "sharpest of each stretch (blurred ones skipped), then structure from motion. "
                               "Needs the video extra: pip install 'warpgs[video]'.",
        epilog="then: warpgs-train --data DIR. Running again with the same video and settings reuses what the "
               "folder holds (and resumes an interrupted run).")
    ap.add_argument("video", help="a video file ffmpeg reads (.mp4, .mov, ...)")
    ap.add_argument("--out", help="the scene folder to write (default: beside the video, named after it)")
    ap.add_argument("--frames", type=int, default=DEFAULT_FRAMES,
                    help=f"how many frames to aim for (default {DEFAULT_FRAMES}, at least {MIN_SHARP_FRAMES}); fewer "
                         f"when the video is shorter or whole stretches are blurred")
    ap.add_argument("--max-size", type=int, default=DEFAULT_MAX_SIZE, metavar="PX",
                    help=f"longest side of the written frames (default {DEFAULT_MAX_SIZE}; 0 keeps the video's)")
    ap.add_argument("--blur-ratio", type=float, default=DEFAULT_BLUR_RATIO, metavar="R",
                    help=f"a frame is blurred when its sharpness is below R x the video's 90th percentile "
                         f"(default {DEFAULT_BLUR_RATIO}; 0 keeps every stretch's sharpest frame)")
    ap.add_argument("--mapper", default="global", choices=("global", "incremental"),
                    help="SfM mapping (default global: GLOMAP, fast on the ordered frames of a video)")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    args = ap.parse_args(argv)
    try:
        out = scene_from_video(args.video, args.out, frames=args.frames, max_size=args.max_size,
                               blur_ratio=args.blur_ratio, mapper=args.mapper, progress=not args.quiet)
    except (ValueError, FileNotFoundError) as e:  # SceneError, TooFewSharpFrames, MissingSceneFile, the extra
        return report_error(PROG, str(e), EXIT_CONFIG)
    print(f"scene in {out.resolve()}\ntrain with: warpgs-train --data {out}")
    return 0


__all__ = ["main", "scene_from_video", "video_scene_dir"]


if __name__ == "__main__":
    import sys

    sys.exit(main())
