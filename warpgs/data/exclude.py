"""Leaving views out of a scene by image name (data.exclude): frames SfM posed on the wrong side of the scene, blurred
or overexposed frames. A pattern is a name, an fnmatch glob, or a range FIRST..LAST of names in natural order
(frame_2 before frame_10), both ends included. The train/test split is kept otherwise, so held-out scores stay
comparable with a run that kept every view."""
from __future__ import annotations

from fnmatch import fnmatchcase
from typing import Sequence

from warpgs.data.pose_checks import natural_key


def excluding(scene, patterns: Sequence[str]):
    """`scene` without the views whose image name matches any of `patterns` (names, globs or FIRST..LAST) in its
    train and test lists; the names left out go to scene.metadata["excluded"]. A pattern that matches no view is an
    error: a typo would otherwise keep the views it meant to drop."""
    if not patterns:
        return scene
    names = [cam.name for cam in scene.native_cameras]
    dropped = set()
    for pattern in patterns:
        if not isinstance(pattern, str) or not pattern.strip():
            raise ValueError(f"data.exclude: expected image names, globs or FIRST..LAST ranges, got {pattern!r}")
        hits = _range(names, pattern, scene.root) if _is_range(names, pattern) else {
            i for i, name in enumerate(names) if fnmatchcase(name, pattern)}
        if not hits:
            raise ValueError(f"data.exclude: {pattern!r} matches no view of the scene at {scene.root} (its views are "
                             f"named like {names[0]!r})")
        dropped |= hits
    out = scene.with_split([i for i in scene.train if i not in dropped], [i for i in scene.test if i not in dropped])
    out.metadata["excluded"] = sorted((names[i] for i in dropped), key=natural_key)
    return out


def _is_range(names: list, pattern: str) -> bool:
    return ".." in pattern and pattern not in names


def _range(names: list, pattern: str, root) -> set:
    """The views from FIRST to LAST in natural name order, both included; each end must be a view's name."""
    first, _, last = pattern.partition("..")
    for end in (first, last):
        if end not in names:
            raise ValueError(f"data.exclude: {pattern!r}: {end!r} is not a view of the scene at {root} (a range "
                             f"FIRST..LAST takes two view names, e.g. {names[0]!r}..{names[-1]!r})")
    order = {name: k for k, name in enumerate(sorted(names, key=natural_key))}
    lo, hi = order[first], order[last]
    if lo > hi:
        raise ValueError(f"data.exclude: {pattern!r}: {first!r} comes after {last!r} in name order")
    return {i for i, name in enumerate(names) if lo <= order[name] <= hi}
