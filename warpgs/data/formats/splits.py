"""Train/test split protocols, plus the split.json file that names image files explicitly."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from warpgs.data.errors import SceneError, read_json, require_file

SPLIT_FILE = "split.json"


def llff_split(num_views: int, n_train: Optional[int] = None, hold_every: int = 8) -> tuple[list[int], list[int]]:
    """The LLFF protocol of the sparse-view literature: every `hold_every`-th view (0, 8, 16, ...) is a test
    view; of the rest, `n_train` views spread evenly (first and last included) train; all of them if None.

    "Evenly" is FSGS's and DNGaussian's rule (their LLFF readers): of the remaining views in sorted order, those
    at positions np.linspace(0, len(rest) - 1, n_train), each rounded half-to-even (Python's round, as np.round).
    fern (20 views): test 0, 8, 16; train 1, 10, 19."""
    if num_views <= 0:
        raise ValueError("llff_split: no views")
    test = list(range(0, num_views, hold_every)) if num_views > 1 else []
    rest = [i for i in range(num_views) if i not in set(test)]
    if n_train is None or n_train >= len(rest):
        if n_train is not None and n_train > len(rest):
            raise ValueError(f"llff_split: asked for {n_train} training views but only {len(rest)} are not held out")
        return rest, test
    if n_train < 1:
        raise ValueError("llff_split: n_train must be at least 1")
    picks = np.round(np.linspace(0, len(rest) - 1, n_train)).astype(int)
    return [rest[i] for i in picks], test


def split_from_names(names: Sequence[str], train_names: Sequence[str], test_names: Sequence[str],
                     source: Optional[Path] = None) -> tuple[list[int], list[int]]:
    """Indices of named views; unknown names are an error naming `source` (the file they came from)."""
    index = {n: i for i, n in enumerate(names)}
    # Accept names with or without their folder prefix, as split files are written both ways.
    by_base = {Path(n).name: i for i, n in enumerate(names)}
    out = []
    for part, wanted in (("train", train_names), ("test", test_names)):
        idx, missing = [], []
        for n in wanted:
            i = index.get(n, by_base.get(Path(n).name))
            (missing.append(n) if i is None else idx.append(i))
        if missing:
            raise SceneError(source, f"{part} split names {len(missing)} view(s) not in the scene, e.g. {missing[:3]}")
        out.append(idx)
    return out[0], out[1]


def read_split_file(path: Path, names: Sequence[str]) -> tuple[list[int], list[int]]:
    """split.json: {"train": [image names], "test": [image names]}."""
    path = require_file(path, "split file")
    data = read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("train"), list):
        raise SceneError(path, 'expected {"train": [names], "test": [names]}')
    return split_from_names(names, data["train"], data.get("test", []), path)


def write_split_file(path: Path, names: Sequence[str], train: Sequence[int], test: Sequence[int]) -> Path:
    path = Path(path)
    path.write_text(json.dumps({"train": [names[i] for i in train], "test": [names[i] for i in test]}, indent=1))
    return path


def resolve_split(root: Path, names: Sequence[str], split: Optional[str | tuple], n_train: Optional[int] = None,
                  ) -> tuple[list[int], list[int]]:
    """Pick a split: an explicit (train, test) index pair; "llff"; "all" (everything trains); or, when None,
    split.json if the folder has one and every view training otherwise."""
    if isinstance(split, tuple):
        return list(split[0]), list(split[1])
    if split is None:
        split = "file" if (Path(root) / SPLIT_FILE).is_file() else "all"
    if split == "file":
        train, test = read_split_file(Path(root) / SPLIT_FILE, names)
        if n_train is not None:
            train = [train[i] for i in np.round(np.linspace(0, len(train) - 1, n_train)).astype(int)]
        return train, test
    if split == "llff":
        return llff_split(len(names), n_train)
    if split == "all":
        if n_train is not None:
            raise ValueError(f"n_train={n_train} needs a split that holds views out ('llff' or a split.json); with "
                             "'all' (the default without split.json) every view trains")
        return list(range(len(names))), []
    raise ValueError(f"unknown split {split!r}; use 'file', 'llff', 'all' or a (train, test) pair")
