"""Finding each view's optional files in the conventional sub-folders of a scene folder.

    <root>/depth/<stem>.exr|.npy|.png      reference depth        (format.json: {"kind": ..., "scale": ...})
    <root>/depth_priors/<stem>.exr|...     depth prior            (format.json as above; default: file declares)
    <root>/masks/<stem>.png or <name>.png  masks
    <root>/labels/<stem>.png               object ids, named in <root>/labels.json
    <root>/features/<stem>.npy             feature maps [h, w, C]
A view without a file in an existing folder simply has none (e.g. labels only for a few evaluation views).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

from warpgs.data.depth.files import DEPTH_EXTENSIONS, KINDS
from warpgs.data.errors import SceneError, read_json
from warpgs.data.formats.image_io import find_sibling
from warpgs.data.scene import MapFormat, ViewFiles

FOLDERS = {
    "depth": (("depth", "depths"), DEPTH_EXTENSIONS),
    "depth_prior": (("depth_priors",), DEPTH_EXTENSIONS),
    "mask": (("masks",), (".png", ".jpg", ".jpeg")),
    "labels": (("labels",), (".png",)),
    "features": (("features",), (".npy",)),
}
FORMAT_FILE = "format.json"
LABELS_FILE = "labels.json"


def discover_view_files(root: Path, names: Sequence[str], image_paths: Sequence[Path]) -> list[ViewFiles]:
    root = Path(root)
    files = [ViewFiles(image=Path(p)) for p in image_paths]
    for attr, (folder_names, exts) in FOLDERS.items():
        folder = next((root / f for f in folder_names if (root / f).is_dir()), None)
        if folder is None:
            continue
        for name, vf in zip(names, files):
            setattr(vf, attr, find_sibling(folder, name, exts))
    return files


def read_map_format(root: Path, attr: str, default: MapFormat) -> MapFormat:
    """format.json of the folder holding `attr` maps ("depth" or "depth_prior"), else `default`."""
    for folder in FOLDERS[attr][0]:
        path = Path(root) / folder / FORMAT_FILE
        if path.is_file():
            data = read_json(path)
            kind = data.get("kind", default.kind)
            if kind is not None and kind not in KINDS:
                raise SceneError(path, f"kind must be one of {KINDS}, got {kind!r}")
            return MapFormat(kind, float(data.get("scale", default.scale)))
    return default


def write_map_format(folder: Path, fmt: MapFormat, **extra) -> Path:
    path = Path(folder) / FORMAT_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"kind": fmt.kind, "scale": fmt.scale, **extra}, indent=1))
    return path


def read_label_names(root: Path) -> dict[int, str]:
    """labels.json: {"1": "red sphere", ...} or a list whose position is the id; id 0 means unlabelled."""
    path = Path(root) / LABELS_FILE
    if not path.is_file():
        return {}
    data = read_json(path)
    try:
        items = enumerate(data) if isinstance(data, list) else ((int(k), v) for k, v in data.items())
        return {int(k): str(v) for k, v in items}
    except (ValueError, AttributeError) as exc:
        raise SceneError(path, 'expected {"<id>": "<name>", ...} or a list of names') from exc
