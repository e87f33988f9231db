"""Coarse-to-fine training (`train.resolution_schedule`): the first steps render and score downscaled views.

A step at 1/f of the resolution renders and scores f² fewer pixels, and early in a run, when the model is coarse, the
fine detail of a full image does not yet steer it (the idea behind DashGaussian's resolution scheduling, CVPR 2025).
The schedule is a list of [step, factor] pairs: from `step` on, training views are served at 1/factor of their
resolution (area-averaged images, intrinsics scaled with the image, as `Camera.scaled`). Evaluation, validation and
every output stay at full resolution. Densification statistics are in NDC and the screen-size rule is a fraction of
the image (train/densify_stats.py), so they mean the same at every scale.
"""
from __future__ import annotations

import copy
from typing import List, Optional, Sequence, Tuple

from warpgs.data.formats.resize import resize_tensor, scaled_size

# View maps resized like the image (area averages) and those resized by nearest sampling (flags and ids).
AREA_MAPS = ("image", "inv_depth_prior", "inv_depth_confidence")
NEAREST_MAPS = ("mask", "inv_depth_valid", "depth", "labels")


def parse_schedule(spec: Optional[Sequence]) -> List[Tuple[int, int]]:
    """[[step, factor], ...] -> [(step, factor)], checked: steps start at 0 and increase, factors are integers >= 1
    (None or []: no schedule)."""
    if not spec:
        return []
    out = []
    for item in spec:
        if not isinstance(item, (list, tuple)) or len(item) != 2:
            raise ValueError(f"train.resolution_schedule: expected [step, factor] pairs, got {item!r}")
        step, factor = item
        if isinstance(step, bool) or isinstance(factor, bool) or int(step) != step or int(factor) != factor:
            raise ValueError(f"train.resolution_schedule: step and factor must be integers, got {item!r}")
        if int(factor) < 1:
            raise ValueError(f"train.resolution_schedule: factor must be >= 1, got {item!r}")
        out.append((int(step), int(factor)))
    if out[0][0] != 0:
        raise ValueError(f"train.resolution_schedule: the first pair must start at step 0, got {list(spec)!r}")
    if any(b[0] <= a[0] for a, b in zip(out, out[1:])):
        raise ValueError(f"train.resolution_schedule: steps must increase, got {list(spec)!r}")
    return out


def factor_at(schedule: Sequence[Tuple[int, int]], step: int) -> int:
    """The downscale factor in force at `step` (1 without a schedule)."""
    factor = 1
    for start, f in schedule:
        if step >= start:
            factor = f
    return factor


def downscaled_view(view, factor: int):
    """A shallow copy of `view` at 1/factor resolution (round(W/factor) x round(H/factor), at least 1 px)."""
    if factor == 1:
        return view
    width, height = scaled_size(view.width, view.height, factor)
    out = copy.copy(view)
    out.width, out.height = width, height
    K = view.K.clone()
    K[0, :] *= width / view.width
    K[1, :] *= height / view.height
    out.K = K
    for name in AREA_MAPS + NEAREST_MAPS:
        value = getattr(view, name, None)
        if value is not None:
            setattr(out, name, resize_tensor(value, width, height, "area" if name in AREA_MAPS else "nearest"))
    return out


class ScaledViews:
    """The training views at the schedule's resolution for a step. Each draw downscales afresh (one area pass on the
    device, microseconds) rather than keeping a second copy of every view."""

    def __init__(self, spec: Optional[Sequence]):
        self.schedule = parse_schedule(spec)

    def factor(self, step: int) -> int:
        return factor_at(self.schedule, step)

    def at(self, view, step: int):
        return downscaled_view(view, self.factor(step))
