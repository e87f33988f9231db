"""Video in (issue 32 item 1): frame choice by spacing and sharpness, the scene folder and its reuse, errors.

The videos are made here with imageio (the `video` extra, in the test extra): a checkerboard sliding across the
frame, with chosen frames box-blurred before encoding. SfM itself is not run on them (a synthetic pattern is no
capture, and it would take minutes); the pipeline test passes a stand-in that records its call."""
import json
import shutil

import numpy as np
import pytest

imageio = pytest.importorskip("imageio.v2")
pytest.importorskip("imageio_ffmpeg")

from warpgs.cli.process import main as process_main  # noqa: E402
from warpgs.data.errors import MissingSceneFile, SceneError  # noqa: E402
from warpgs.data.video import (TooFewSharpFrames, is_video, select_frames, sharpness, video_scene_dir,  # noqa: E402
                               video_to_scene)
from warpgs.data.video.scene import finished_scene  # noqa: E402
from warpgs.data.video.decode import iter_frames  # noqa: E402


def _pattern(t: int, h: int = 96, w: int = 128) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    v = (((x + 3 * t) // 8 + (y + t) // 8) % 2).astype(np.float32)
    return np.repeat((v * 200 + 30)[..., None], 3, axis=2).astype(np.uint8)


def _blur(img: np.ndarray, r: int = 4) -> np.ndarray:
    f = img.astype(np.float32)
    for _ in range(3):  # three box passes: close to a Gaussian of sigma ~4 px, as a shaken phone gives
        for axis in (0, 1):
            f = sum(np.roll(f, k, axis=axis) for k in range(-r, r + 1)) / (2 * r + 1)
    return f.astype(np.uint8)


def make_video(path, n: int, blurred) -> None:
    writer = imageio.get_writer(path, fps=10, quality=9, macro_block_size=1, ffmpeg_log_level="error")
    for t in range(n):
        writer.append_data(_blur(_pattern(t)) if t in blurred else _pattern(t))
    writer.close()


def scores_of(path):
    return [sharpness(f) for f in iter_frames(path)]


def test_blurred_frames_are_never_chosen_and_order_is_kept(tmp_path):
    video = tmp_path / "clip.mp4"
    blurred = {t for t in range(60) if t % 3 == 1}
    make_video(video, 60, blurred)
    scores = scores_of(video)
    assert len(scores) == 60
    sharp = [s for t, s in enumerate(scores) if t not in blurred]
    assert max(scores[t] for t in blurred) < 0.2 * min(sharp)  # the measure tells them apart after H.264
    sel = select_frames(scores, 20, min_frames=5)
    assert len(sel.indices) == 20 and sel.blurred_windows == 0
    assert not set(sel.indices) & blurred
    assert sel.indices == sorted(sel.indices) and len(set(sel.indices)) == 20
    gaps = np.diff(sel.indices)
    assert gaps.min() >= 1 and gaps.max() <= 5  # evenly spread: one per stretch of 3 frames


def test_a_blurred_stretch_gives_no_frames(tmp_path):
    video = tmp_path / "shaky.mp4"
    blurred = set(range(20, 40))
    make_video(video, 60, blurred)
    sel = select_frames(scores_of(video), 12, min_frames=5)
    assert not set(sel.indices) & blurred
    assert sel.blurred_windows == 4 and len(sel.indices) == 8  # windows of 5 frames; 20..39 is four of them
    assert sel.indices == sorted(sel.indices)


def test_fewer_frames_than_the_target_keeps_each_sharp_one():
    scores = [10.0, 0.1, 12.0, 11.0]
    sel = select_frames(scores, 200, min_frames=2)
    assert sel.windows == 4 and sel.indices == [0, 2, 3] and sel.blurred_windows == 1


def test_too_few_sharp_frames_is_a_clear_error(tmp_path):
    video = tmp_path / "blurry.mp4"
    make_video(video, 30, set(range(4, 30)))
    with pytest.raises(TooFewSharpFrames, match=r"blurry\.mp4: only \d+ sharp frame"):
        select_frames(scores_of(video), 20, min_frames=10, source=str(video))


def test_unreadable_and_missing_videos_name_the_file(tmp_path, capsys):
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"this is no video")
    with pytest.raises(SceneError, match=r"broken\.mp4: not a readable video"):
        list(iter_frames(bad))
    assert process_main([str(bad), "--out", str(tmp_path / "scene")]) == 2
    err = capsys.readouterr().err
    assert "warpgs-process: error:" in err and "broken.mp4" in err and "not a readable video" in err
    with pytest.raises(MissingSceneFile, match="nothere.mp4: video file not found"):
        video_to_scene(tmp_path / "nothere.mp4")


def test_settings_that_cannot_succeed_are_refused_before_decoding(tmp_path, capsys):
    # Settings that can never succeed (fewer than the 10 frames SfM needs, a ratio outside [0, 1)) are named
    # before minutes of decoding, and leave no scene folder behind.
    video = tmp_path / "clip.mp4"
    make_video(video, 12, set())
    assert process_main([str(video), "--frames", "5"]) == 2
    assert "frames: expected at least 10" in capsys.readouterr().err
    assert not (tmp_path / "clip").exists()
    with pytest.raises(ValueError, match="frames: expected at least 4"):
        select_frames([1.0] * 12, 3, min_frames=4)
    assert process_main([str(video), "--blur-ratio", "1.5"]) == 2
    assert "blur_ratio: expected a value in [0, 1), got 1.5" in capsys.readouterr().err
    assert not (tmp_path / "clip").exists()


def test_missing_extra_says_what_to_install(tmp_path, monkeypatch, capsys):
    video = tmp_path / "clip.mp4"
    video.write_bytes(b"x")
    monkeypatch.setitem(__import__("sys").modules, "imageio_ffmpeg", None)  # import fails as if not installed
    assert process_main([str(video)]) == 2
    assert "pip install 'warpgs[video]'" in capsys.readouterr().err


class _SfmStandIn:
    def __init__(self):
        self.calls = []

    def __call__(self, images, out, **kwargs):
        self.calls.append((images, out, kwargs))
        (out / "sparse" / "0").mkdir(parents=True)
        return out / "sparse" / "0"


def test_video_to_scene_writes_frames_runs_sfm_once_and_reuses(tmp_path):
    video = tmp_path / "clip.mp4"
    make_video(video, 40, {t for t in range(40) if t % 4 == 2})
    sfm = _SfmStandIn()
    out = video_to_scene(video, frames=10, min_frames=5, progress=False, sfm=sfm)
    assert out == tmp_path / "clip" == video_scene_dir(video)
    names = sorted(p.name for p in (out / "images").iterdir())
    indices = [int(n[len("frame_"):-len(".jpg")]) for n in names]
    assert len(names) == 10 and all(i % 4 != 2 for i in indices) and indices == sorted(indices)
    record = json.loads((out / "video.json").read_text())
    assert record["extracted"]["indices"] == indices and record["extracted"]["total"] == 40
    assert len(sfm.calls) == 1 and sfm.calls[0][0] == out / "images" and sfm.calls[0][2]["mapper"] == "global"
    assert finished_scene(video)  # what warpgs-train --data clip.mp4 checks: trains on it, whatever --frames made it
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "images").iterdir()}
    # Same video, same settings: nothing is redone.
    assert video_to_scene(video, frames=10, min_frames=5, progress=False, sfm=sfm) == out
    assert len(sfm.calls) == 1
    assert {p.name: p.stat().st_mtime_ns for p in (out / "images").iterdir()} == stamps
    # An interrupted SfM (no model yet) is resumed without extracting again.
    (out / "sparse" / "0").rmdir()
    assert not finished_scene(video)
    video_to_scene(video, frames=10, min_frames=5, progress=False, sfm=sfm)
    assert len(sfm.calls) == 2
    assert {p.name: p.stat().st_mtime_ns for p in (out / "images").iterdir()} == stamps
    # Other settings on the same folder are refused, not overwritten.
    with pytest.raises(SceneError, match=r"clip: made from another video or other settings .*frames"):
        video_to_scene(video, frames=12, min_frames=5, progress=False, sfm=sfm)


def test_a_video_and_its_scene_moved_together_are_reused(tmp_path):
    """The scene folder knows its video by contents, not by path or time stamp: moved (or copied) elsewhere
    together, the video trains on the scene made before; another video is refused."""
    video = tmp_path / "a" / "clip.mp4"
    video.parent.mkdir()
    make_video(video, 24, set())
    sfm = _SfmStandIn()
    video_to_scene(video, frames=6, min_frames=3, progress=False, sfm=sfm)
    moved = tmp_path / "b"
    shutil.copytree(tmp_path / "a", moved)  # new path; the copy's time stamps are new too
    shutil.rmtree(tmp_path / "a")
    assert finished_scene(moved / "clip.mp4")
    video_to_scene(moved / "clip.mp4", frames=6, min_frames=3, progress=False, sfm=sfm)
    assert len(sfm.calls) == 1  # nothing redone
    other = moved / "clip2.mp4"
    make_video(other, 24, {3})
    assert not finished_scene(other, moved / "clip")
    with pytest.raises(SceneError, match=r"made from another video or other settings .*fingerprint"):
        video_to_scene(other, moved / "clip", frames=6, min_frames=3, progress=False, sfm=sfm)


def test_a_scene_made_by_the_first_record_format_is_reused_and_upgraded(tmp_path):
    video = tmp_path / "clip.mp4"
    make_video(video, 24, set())
    sfm = _SfmStandIn()
    out = video_to_scene(video, frames=6, min_frames=3, progress=False, sfm=sfm)
    record = json.loads((out / "video.json").read_text())
    st = video.stat()  # the first format: the resolved path, size and time stamp
    record["settings"] = {"video": str(video.resolve()), "bytes": st.st_size, "mtime_ns": st.st_mtime_ns,
                          "frames": 6, "max_size": record["settings"]["max_size"],
                          "blur_ratio": record["settings"]["blur_ratio"]}
    (out / "video.json").write_text(json.dumps(record))
    assert finished_scene(video)
    video_to_scene(video, frames=6, min_frames=3, progress=False, sfm=sfm)
    assert len(sfm.calls) == 1
    upgraded = json.loads((out / "video.json").read_text())["settings"]
    assert "fingerprint" in upgraded and "mtime_ns" not in upgraded and upgraded["video"] == "clip.mp4"


def test_a_foreign_folder_is_not_overwritten(tmp_path):
    video = tmp_path / "clip.mp4"
    make_video(video, 12, set())
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    with pytest.raises(SceneError, match="mine: exists and holds no video.json"):
        video_to_scene(video, mine, frames=5, min_frames=2, progress=False, sfm=_SfmStandIn())
    assert (mine / "notes.txt").read_text() == "keep"
    # A folder that cannot be made (beside a video on a read-only card, say) is a named error, not a traceback.
    blocked = tmp_path / "afile"
    blocked.write_text("")
    with pytest.raises(SceneError, match=r"afile/scene: cannot write the scene folder .*warpgs-process VIDEO --out"):
        video_to_scene(video, blocked / "scene", frames=10, min_frames=2, progress=False, sfm=_SfmStandIn())


def test_video_extensions():
    assert is_video("a/clip.MP4") and is_video("b.mov") and not is_video("scene") and not is_video("x.ply")
