"""How big a scene is, for the rule that prunes primitives too large for it (the strategy's world-size rule).

3DGS's extent, `Scene.camera_extent()`, is 1.1 x the largest distance of a camera centre from their mean. That
is the scene's size when the cameras walk around their subject, but far too small when they barely move (a
forward-facing phone sweep, a tripod pan, a light-field array): the content then lies many baselines away, and
0.1 x that extent is a few pixels wide at the subject's depth, so the world-size rule deletes the scene.

`content_extent` is 1.1 x the larger of the cameras' radius and the half-width of what a camera sees at the
scene's typical depth (depth x tan(half field of view), median over the cameras). The depth is the
median depth of the SfM points in front of the camera, else the distance to the point the optical axes converge
on; with neither (parallel axes, no points) only the cameras' radius counts. Around an object the cameras'
radius is the larger (the subject fills the view at about the orbit radius), so 3DGS's value is unchanged there.
Where the depth term wins, the default rule (scale > 0.1 x extent) prunes, at the typical depth, primitives whose
3-sigma footprint exceeds ~15% of the image's larger side: gsplat's screen-size threshold.
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from warpgs.data.camera import Camera, optical_axes_focus

MAX_POINTS = 20_000  # a strided subset is plenty for a median and keeps this O(cameras x 20k)


def camera_radius(cameras: Sequence[Camera]) -> float:
    """The largest distance of a camera centre from the centres' mean (Scene.camera_extent is 1.1 x this)."""
    centres = np.stack([c.center for c in cameras])
    return float(np.linalg.norm(centres - centres.mean(0), axis=1).max())


def typical_depths(cameras: Sequence[Camera], points: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
    """[C] depth of the scene's content from each camera, or None when nothing says where the content is."""
    if points is not None and len(points):
        pts = np.asarray(points, dtype=np.float64)[:: max(1, len(points) // MAX_POINTS)]
        depths = []
        for cam in cameras:
            z = cam.world_to_camera(pts)[:, 2]
            z = z[z > 0]
            if len(z):
                depths.append(np.median(z))
        if depths:
            return np.asarray(depths)
    if len(cameras) > 1:
        focus = optical_axes_focus(cameras, max_condition=1e6)
        if focus is not None:
            z = np.array([c.world_to_camera(focus)[0, 2] for c in cameras])
            if (z > 0).any():
                return z[z > 0]
    return None


def content_extent(cameras: Sequence[Camera], points: Optional[np.ndarray] = None) -> float:
    """1.1 x max(cameras' radius, median depth x tan(half field of view)); 1.0 if both are 0. See the module doc."""
    if not cameras:
        raise ValueError("content_extent: no cameras")
    radius = camera_radius(cameras)
    depths = typical_depths(cameras, points)
    if depths is not None:
        half_fov = np.median([0.5 * max(c.width / c.fx, c.height / c.fy) for c in cameras])
        radius = max(radius, float(np.median(depths)) * float(half_fov))
    return 1.1 * radius if radius > 0 and np.isfinite(radius) else 1.0


def scene_content_extent(scene) -> float:
    """content_extent over the scene's training cameras (all when none trains; as Scene.camera_extent, so the two
    agree around an object) and its SfM points."""
    points = scene.points.xyz if scene.points is not None else None
    return content_extent([scene.cameras[i] for i in scene.train] or scene.cameras, points)
