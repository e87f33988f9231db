"""video_to_scene: a video file -> an ordinary COLMAP scene folder (images/ + sparse/0) that `--data DIR` loads.

Stages, each with a progress line: score (decode every frame once, sharpness of each), extract (decode again,
write the chosen frames as JPEG), sfm (data/sfm/run.py). The folder's video.json records the settings and which
stages finished, so a second call with the same video and settings reuses what exists (an interrupted call
resumes at the stage it stopped in); a folder made with other settings, or not made by us, is refused rather
than overwritten.
"""
from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path
from typing import Callable, Optional

from PIL import Image

from warpgs.data.errors import MissingSceneFile, PathLike, SceneError, read_json
from warpgs.data.video.decode import iter_frames, require_video_support
from warpgs.data.video.sharpness import (DEFAULT_BLUR_RATIO, MIN_SHARP_FRAMES, check_selection, select_frames,
                                        sharpness)
from warpgs.utils.atomic_file import atomic_write_bytes
from warpgs.utils.progress import Stages

DEFAULT_FRAMES = 200
DEFAULT_MAX_SIZE = 1600  # longest side of the written frames (SfM extracts features at 1600 px anyway)
RECORD = "video.json"
STAGES = ("score", "extract", "sfm")
JPEG_QUALITY = 95
ELSEWHERE = "make the scene in another folder: warpgs-process VIDEO --out DIR, then warpgs-train --data DIR"


def video_scene_dir(video: PathLike) -> Path:
    """Where `warpgs-train --data clip.mp4` puts the scene: a folder beside the video named after it (clip/)."""
    return Path(video).with_suffix("")


FINGERPRINT_BYTES = 1 << 20  # read from each end of the video


def _fingerprint(video: Path) -> str:
    """The video's identity wherever it lies: a digest of its size and of its first and last MiB (moving or copying
    the video and its scene folder elsewhere, which changes the path and may change the time stamp, keeps it)."""
    size = video.stat().st_size
    h = hashlib.sha1(str(size).encode())
    with open(video, "rb") as f:
        h.update(f.read(FINGERPRINT_BYTES))
        if size > FINGERPRINT_BYTES:
            f.seek(max(FINGERPRINT_BYTES, size - FINGERPRINT_BYTES))
            h.update(f.read(FINGERPRINT_BYTES))
    return h.hexdigest()


def _settings(video: Path, frames: int, max_size: int, blur_ratio: float) -> dict:
    return {"video": video.name, "bytes": video.stat().st_size, "fingerprint": _fingerprint(video),
            "frames": int(frames), "max_size": int(max_size), "blur_ratio": float(blur_ratio)}


VIDEO_KEYS = ("bytes", "fingerprint")  # what says "the same video" (the name may change with the file's)


def _differences(made: dict, mine: dict, keys) -> list:
    return sorted(k for k in keys if not isinstance(made, dict) or made.get(k) != mine[k])


def _upgraded(record: dict, video: Path) -> dict:
    """A record of the first format (the video's resolved path, size and time stamp, no fingerprint) that names
    this very file, given the fingerprint, so folders made then are reused and can move from now on."""
    made = record.get("settings") if isinstance(record, dict) else None
    if not isinstance(made, dict) or "fingerprint" in made or "mtime_ns" not in made:
        return record
    st = video.stat()
    if (made.get("video"), made.get("bytes"), made.get("mtime_ns")) == (str(video.resolve()), st.st_size,
                                                                        st.st_mtime_ns):
        record["settings"] = {**{k: v for k, v in made.items() if k != "mtime_ns"},
                              "video": video.name, "fingerprint": _fingerprint(video)}
    return record


def finished_scene(video: PathLike, out: Optional[PathLike] = None) -> bool:
    """Whether `out` (default video_scene_dir(video)) holds a finished scene made from this very video (the same
    contents, wherever it now lies), whatever frame settings it was made with: `warpgs-train --data VIDEO` trains
    on what an earlier `warpgs-process VIDEO --frames N` made."""
    video = Path(video)
    out = Path(out) if out is not None else video_scene_dir(video)
    try:
        record = _upgraded(read_json(out / RECORD), video)
        same = not _differences(record["settings"], _settings(video, 1, 0, 0.0), VIDEO_KEYS)
        return bool(same and _frames_written(out, record) and _sfm_done(out, record))
    except (OSError, ValueError, KeyError, TypeError):
        return False


def _frames_written(out: Path, record: dict) -> bool:
    """Whether the record's extract stage finished and its frames are all still in out/images."""
    done = record.get("extracted")
    return done is not None and all((out / "images" / _frame_name(i)).is_file() for i in done["indices"])


def _sfm_done(out: Path, record: dict) -> bool:
    return bool(record.get("sfm")) and (out / "sparse" / "0").is_dir()


def _write_record(out: Path, record: dict) -> None:
    atomic_write_bytes(out / RECORD, (json.dumps(record, indent=1) + "\n").encode())


def _claim(out: Path, video: Path, settings: dict) -> dict:
    """The folder's record when it was made from this video with these settings (a fresh one for a new or
    empty folder); SceneError naming the folder otherwise."""
    path = out / RECORD
    if path.is_file():
        record = read_json(path)
        first_format = isinstance(record, dict) and "mtime_ns" in (record.get("settings") or {})
        record = _upgraded(record, video)
        old = record.get("settings") if isinstance(record, dict) else None
        diff = _differences(old, settings, VIDEO_KEYS + ("frames", "max_size", "blur_ratio"))
        if first_format and not diff:
            _write_record(out, record)
        if diff:
            raise SceneError(out, f"made from another video or other settings (differs in {diff}: "
                                  f"{ {k: (old or {}).get(k) for k in diff} }); delete it to redo it, or "
                                  f"{ELSEWHERE}")
        return record
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise SceneError(out, f"exists and holds no {RECORD} (not a folder made from a video); {ELSEWHERE}")
    record = {"settings": settings}
    try:  # beside the video by default, which may be read-only (a card, a share)
        out.mkdir(parents=True, exist_ok=True)
        _write_record(out, record)
    except OSError as exc:
        raise SceneError(out, f"cannot write the scene folder ({exc.strerror or exc}); {ELSEWHERE}") from exc
    return record


def _jpeg(frame, max_size: int) -> bytes:
    img = Image.fromarray(frame)
    if max_size and max(img.size) > max_size:
        scale = max_size / max(img.size)
        img = img.resize((max(1, round(img.width * scale)), max(1, round(img.height * scale))), Image.LANCZOS)
    buf = io.BytesIO()
    img.save(buf, format="JPEG", quality=JPEG_QUALITY)
    return buf.getvalue()


def _frame_name(index: int) -> str:
    return f"frame_{index:06d}.jpg"  # the source frame number: name order is video order (SfM's sequential pairs)


def video_to_scene(video: PathLike, out: Optional[PathLike] = None, *, frames: int = DEFAULT_FRAMES,
                   max_size: int = DEFAULT_MAX_SIZE, blur_ratio: float = DEFAULT_BLUR_RATIO,
                   min_frames: int = MIN_SHARP_FRAMES, mapper: str = "global", progress: bool = True,
                   sfm: Optional[Callable] = None) -> Path:
    """Turn `video` into a scene folder `out` (default video_scene_dir(video)); returns it.

    frames: how many frames to aim for (fewer when windows hold only blurred frames or the video is shorter).
    max_size: longest side of the written frames (0 keeps the video's size). mapper: run_sfm's ("global" suits
    the ordered frames of a video). sfm: run_sfm by default (tests pass a stand-in).
    Errors: MissingSceneFile (no such video), SceneError (unreadable video, a folder made otherwise),
    TooFewSharpFrames, VideoUnavailable (the `video` extra is not installed)."""
    video = Path(video)
    if not video.is_file():
        raise MissingSceneFile(video, "video file")
    check_selection(frames, blur_ratio, min_frames)  # before decoding: bad settings could never succeed
    if max_size < 0:
        raise ValueError(f"max_size: expected 0 (keep) or a positive number of pixels, got {max_size}")
    require_video_support()
    out = Path(out) if out is not None else video_scene_dir(video)
    record = _claim(out, video, _settings(video, frames, max_size, blur_ratio))
    stages = Stages(STAGES, prefix="video", enabled=progress)
    images = out / "images"

    if not _frames_written(out, record):
        with stages.run("score", f"{video.name}: sharpness of every frame"):
            scores = []
            for frame in iter_frames(video):
                scores.append(sharpness(frame))
                if len(scores) % 500 == 0:
                    stages.report(f"scored {len(scores)} frames")
        selection = select_frames(scores, frames, blur_ratio=blur_ratio, min_frames=min_frames, source=str(video))
        stages.report(f"{len(scores)} frames; keeping {len(selection.indices)} of {selection.windows} evenly spaced "
                      f"({selection.blurred_windows} stretches held only blurred frames)")
        with stages.run("extract", f"{len(selection.indices)} frames to {images}"):
            for old in images.glob("frame_*.jpg") if images.is_dir() else ():  # an interrupted earlier extract
                old.unlink()
            wanted = set(selection.indices)
            for i, frame in enumerate(iter_frames(video)):
                if i in wanted:
                    atomic_write_bytes(images / _frame_name(i), _jpeg(frame, max_size))
                if i >= selection.indices[-1]:
                    break
        record["extracted"] = {"total": selection.total, "indices": selection.indices,
                               "threshold": selection.threshold}
        _write_record(out, record)
    else:
        stages.report(f"reusing {len(record['extracted']['indices'])} frames in {images}")

    if not _sfm_done(out, record):
        if sfm is None:
            from warpgs.data.sfm.run import run_sfm as sfm
        with stages.run("sfm", f"{len(record['extracted']['indices'])} frames, {mapper} mapping"):
            sfm(images, out, matcher="auto", mapper=mapper, progress=progress)
        record["sfm"] = {"mapper": mapper}
        _write_record(out, record)
    else:
        stages.report(f"reusing the SfM model in {out / 'sparse' / '0'}")
    return out
