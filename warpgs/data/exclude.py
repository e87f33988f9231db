"""Leaving views out of a scene by image name (data.exclude): frames SfM posed on the wrong side of the scene, blurred
or overexposed frames. The train/test split is kept otherwise, so held-out scores stay comparable with a run that
kept every view."""
from __future__ import annotations

from fnmatch import fnmatchcase
from typing import Sequence


def excluding(scene, patterns: Sequence[str]):
    """`scene` without the views whose image name matches any of `patterns` (exact names or fnmatch globs) in its
    train and test lists; the names left out go to scene.metadata["excluded"]. A pattern that matches no view is an
    error: a typo would otherwise keep the views it meant to drop."""
    if not patterns:
        return scene
    names = [cam.name for cam in scene.native_cameras]
    dropped = set()
    for pattern in patterns:
        if not isinstance(pattern, str) or not pattern.strip():
            raise ValueError(f"data.exclude: expected image names or globs, got {pattern!r}")
        hits = {i for i, name in enumerate(names) if fnmatchcase(name, pattern)}
        if not hits:
            raise ValueError(f"data.exclude: {pattern!r} matches no view of the scene at {scene.root} (its views are "
                             f"named like {names[0]!r})")
        dropped |= hits
    out = scene.with_split([i for i in scene.train if i not in dropped], [i for i in scene.test if i not in dropped])
    out.metadata["excluded"] = sorted(names[i] for i in dropped)
    return out
