"""Pose sanity for video captures: consecutive frames of a video are a few degrees and a short step apart, so a
pose that turns half around between two neighbouring frames was put on the wrong side of the scene by SfM (a
symmetric object, repeated texture). Such frames contradict the others; training fits them anyway and held-out
scores turn erratic (docs/real_captures.md: beer). Photo collections have no order and are not judged."""
from __future__ import annotations

import re
from typing import Optional, Sequence

import numpy as np

from warpgs.data.camera import Camera
from warpgs.data.sfm.sim3 import rotation_angle_deg

# A set is judged as a video only when its frames, in name order, form a smooth path: the median step turns less
# than this and the jumps are rare (unordered photo collections turn far more between names).
VIDEO_MEDIAN_TURN_DEG = 15.0
VIDEO_MAX_JUMP_FRACTION = 0.1
# A jump at least this large is read as SfM folding an orbit in half (a symmetric subject seen from opposite sides).
HALF_TURN_DEG = 150.0


def natural_key(name: str) -> list:
    """Sort key that puts frame_2 before frame_10."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def turn_degrees(a: Camera, b: Camera) -> float:
    """The rotation between two cameras' orientations, in degrees."""
    return rotation_angle_deg(np.asarray(b.viewmat, np.float64)[:3, :3] @ np.asarray(a.viewmat, np.float64)[:3, :3].T)


def continuity(cameras: Sequence[Camera], max_turn: float = 60.0, max_step: float = 5.0) -> dict:
    """Steps between consecutive frames in natural name order, and the jumps among them: a step turning more
    than max_turn degrees, or moving more than max_step times the median distance."""
    cams = sorted(cameras, key=lambda c: natural_key(c.name))
    if len(cams) < 3:
        raise ValueError(f"continuity: need at least 3 frames, got {len(cams)}")
    turns = [turn_degrees(a, b) for a, b in zip(cams, cams[1:])]
    steps = [float(np.linalg.norm(b.center - a.center)) for a, b in zip(cams, cams[1:])]
    median_turn, median_step = float(np.median(turns)), float(np.median(steps))
    jumps = [{"from": cams[i].name, "to": cams[i + 1].name, "turn_deg": round(t, 2),
              "step_over_median": round(s / max(median_step, 1e-12), 2)}
             for i, (t, s) in enumerate(zip(turns, steps)) if t > max_turn or s > max_step * median_step]
    return {"frames": len(cams), "median_turn_deg": round(median_turn, 2), "median_step": round(median_step, 5),
            "max_turn_deg": round(max(turns), 2), "jumps": jumps}


def video_pose_jumps(cameras: Sequence[Camera]) -> list:
    """The jumps of a set that looks like a video (see the module doc), else []: what a loader warns about."""
    if len(cameras) < 10:
        return []
    found = continuity(cameras)
    steps = found["frames"] - 1
    if found["median_turn_deg"] > VIDEO_MEDIAN_TURN_DEG or len(found["jumps"]) > VIDEO_MAX_JUMP_FRACTION * steps:
        return []
    return found["jumps"]


def scene_pose_jumps(scene) -> list:
    """video_pose_jumps over all of a scene's frames (so that gaps left by data.exclude are not judged as steps),
    keeping the jumps between two views the scene still trains or scores on: one into a left-out frame is moot."""
    used = {scene.native_cameras[i].name for i in [*scene.train, *scene.test]}
    return [j for j in video_pose_jumps(scene.native_cameras) if j["from"] in used and j["to"] in used]


def folded_halves(cameras: Sequence[Camera], jumps: Optional[list] = None) -> list:
    """When every jump of a video (video_pose_jumps) is about half a turn, SfM has likely folded an orbit around a
    symmetric subject in half (beer: the azimuth around the can runs over about the same half circle four times).
    The runs of frames between jumps then sit alternately on the two sides of the fold, each side consistent in
    itself.
    jumps: the cameras' jumps as a caller already found them (continuity's, with its own thresholds); default
    video_pose_jumps(cameras). Returns the two sides, the larger first, each as its runs [(first name, last name,
    frames), ...]; [] when there is no jump or a jump is not a half turn."""
    jumps = video_pose_jumps(cameras) if jumps is None else jumps
    if not jumps or any(j["turn_deg"] < HALF_TURN_DEG for j in jumps):
        return []
    starts = {j["to"] for j in jumps}
    runs: list = []
    for name in sorted((c.name for c in cameras), key=natural_key):
        if not runs or name in starts:
            runs.append([])
        runs[-1].append(name)
    sides = sorted([runs[0::2], runs[1::2]], key=lambda side: -sum(len(r) for r in side))
    return [[(r[0], r[-1], len(r)) for r in side] for side in sides]


def side_ranges(side: list) -> tuple[str, int]:
    """One side of folded_halves as data.exclude ranges ("0000.jpg..0013.jpg, 0035.jpg..0052.jpg") and its
    number of frames."""
    return ", ".join(f"{first}..{last}" for first, last, _ in side), sum(n for *_, n in side)
