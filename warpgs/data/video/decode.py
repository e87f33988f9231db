"""Video frames through imageio's FFMPEG plugin and the ffmpeg binary of imageio-ffmpeg (the optional extra
`video`), with errors that name the file."""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from warpgs.data.errors import MissingSceneFile, PathLike, SceneError

INSTALL_HINT = "pip install 'warpgs[video]'"
# What `--data` takes for a video rather than a scene folder (lower case; any container ffmpeg reads works
# through warpgs-process, these are the ones recognised by name).
VIDEO_EXTENSIONS = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mts", ".3gp")


class VideoUnavailable(RuntimeError):
    """imageio or its ffmpeg binary (imageio-ffmpeg) is not installed."""


def is_video(path: PathLike) -> bool:
    """Whether `path` names a video file by its extension (it need not exist)."""
    return Path(path).suffix.lower() in VIDEO_EXTENSIONS


def require_video_support(purpose: str = "reading video") -> None:
    """Raise VideoUnavailable, naming the extra to install, unless imageio can run ffmpeg."""
    try:
        import imageio.v2  # noqa: F401
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as exc:
        raise VideoUnavailable(f"{purpose} needs imageio and imageio-ffmpeg ({exc}); {INSTALL_HINT}") from exc


def iter_frames(path: PathLike) -> Iterator[np.ndarray]:
    """The frames of a video in order, each [H, W, 3] uint8 (ffmpeg applies the rotation phones record).
    MissingSceneFile when there is no such file; SceneError naming it when ffmpeg cannot decode it."""
    path = Path(path)
    if not path.is_file():
        raise MissingSceneFile(path, "video file")
    require_video_support()
    import imageio.v2 as imageio

    try:
        reader = imageio.get_reader(path, format="FFMPEG", mode="I")
    except Exception as exc:  # imageio raises OSError / RuntimeError / ValueError by failure
        raise SceneError(path, f"not a readable video ({_first_line(exc)})") from exc
    count = 0
    try:
        while True:
            try:
                frame = reader.get_next_data()
            except IndexError:  # the end of the stream
                break
            except Exception as exc:
                raise SceneError(path, f"video unreadable after {count} frames ({_first_line(exc)})") from exc
            count += 1
            yield np.asarray(frame)[..., :3]
    finally:
        reader.close()
    if count == 0:
        raise SceneError(path, "the video holds no frames")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__
