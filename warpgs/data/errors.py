"""Errors raised by scene loading. Every message names the file (or folder) at fault."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Optional, Union

PathLike = Union[str, Path]


class SceneError(ValueError):
    """A scene file exists but is unreadable, truncated, mis-sized or inconsistent with the rest of the scene."""

    def __init__(self, path: Optional[PathLike], problem: str):
        self.path = None if path is None else Path(path)
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)


class MissingSceneFile(FileNotFoundError):
    """A file or folder the scene refers to does not exist."""

    def __init__(self, path: PathLike, what: str = "file"):
        self.path = Path(path)
        self.what = what
        super().__init__(f"{self.path}: {what} not found")


class DepthModelUnavailable(RuntimeError):
    """An optional learned depth model was asked for but its package or weights are not available locally."""


def read_json(path: PathLike) -> Any:
    """The parsed contents of a scene's JSON file, or SceneError naming it when it is not valid JSON (UTF-8)."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(path, f"not valid JSON ({exc})") from exc


def require_file(path: PathLike, what: str = "file") -> Path:
    """Return `path` as a Path, or raise MissingSceneFile naming it and what it was meant to be."""
    path = Path(path)
    if not path.is_file():
        raise MissingSceneFile(path, what)
    return path
