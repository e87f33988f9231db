"""Camera paths for `warpgs-render --orbit N`: a circle around what the scene's cameras look at."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from warpgs.data.camera import Camera, look_at, optical_axes_focus


def orbit_cameras(cameras: Sequence[Camera], n: int, points: Optional[np.ndarray] = None) -> list:
    """n cameras (intrinsics and size of cameras[0]) on a circle around the scene's up axis through the focus
    of the cameras, at their median distance and height. For a forward-facing rig (parallel axes) the circle
    lies in the rig's plane instead, with radius the rig's spread, looking at the median point depth."""
    if n < 1:
        raise ValueError(f"orbit: expected a positive number of views, got {n}")
    cams = list(cameras)
    ref = cams[0]
    centres = np.stack([c.center for c in cams])
    up = -np.mean([c.viewmat[1, :3] for c in cams], 0)  # image "down" is camera +y
    up /= max(np.linalg.norm(up), 1e-12)
    focus = optical_axes_focus(cams, max_condition=1e4)
    out = []
    if focus is not None:
        rel = centres - focus
        height = float(np.median(rel @ up))
        horiz = rel - np.outer(rel @ up, up)
        radius = float(np.median(np.linalg.norm(horiz, axis=1)))
        e1 = horiz[0] / max(np.linalg.norm(horiz[0]), 1e-12)
        e2 = np.cross(up, e1)
        for k in range(n):
            a = 2 * np.pi * k / n
            eye = focus + height * up + radius * (np.cos(a) * e1 + np.sin(a) * e2)
            out.append(Camera(ref.K, look_at(eye, focus, up), ref.width, ref.height, name=f"orbit_{k:03d}.png"))
        return out
    forward = np.mean([c.forward for c in cams], 0)
    forward /= np.linalg.norm(forward)
    mid = centres.mean(0)
    spread = float(np.max(np.linalg.norm(centres - mid, axis=1))) or 0.1
    depth = 1.0
    if points is not None and len(points):
        depth = float(np.median((np.asarray(points) - mid) @ forward)) or 1.0
    target = mid + depth * forward
    e1 = np.cross(forward, up)
    e1 /= max(np.linalg.norm(e1), 1e-12)
    e2 = np.cross(forward, e1)
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = mid + spread * (np.cos(a) * e1 + np.sin(a) * e2)
        out.append(Camera(ref.K, look_at(eye, target, up), ref.width, ref.height, name=f"orbit_{k:03d}.png"))
    return out
