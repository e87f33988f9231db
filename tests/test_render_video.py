"""`warpgs-render --orbit N --video`: an MP4 beside the PNGs (read back with imageio: frame count and size),
written atomically (a crash leaves no half MP4 and keeps an older one), and a clear error naming the extra
when imageio-ffmpeg is missing."""
import os
import sys

import numpy as np
import pytest

from train_fixtures import quick_overrides
from warpgs.cli.commands import render_main

imageio = pytest.importorskip("imageio.v2", reason="the video extra: pip install 'warpgs[video]'")
pytest.importorskip("imageio_ffmpeg", reason="the video extra: pip install 'warpgs[video]'")
from warpgs.cli.video import Mp4Writer  # noqa: E402


def read_frames(path):
    with imageio.get_reader(path, format="FFMPEG") as reader:
        return [np.asarray(f) for f in reader]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from warpgs.train.trainer import Trainer

    out = tmp_path_factory.mktemp("run")
    Trainer(None, overrides=quick_overrides(out, steps=2), quiet=True).fit()  # 64x48 views
    return out


def test_orbit_video_beside_the_pngs(run_dir, tmp_path, capsys):
    out = tmp_path / "orbit"
    assert render_main(["--model", str(run_dir), "--orbit", "5", "--video", "--fps", "10", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["orbit.mp4"] + [f"orbit_{k:03d}.png" for k in range(5)]
    frames = read_frames(out / "orbit.mp4")
    assert len(frames) == 5
    assert all(f.shape == (48, 64, 3) for f in frames)
    # The video shows the renders: each frame is its PNG up to H.264's loss.
    png = imageio.imread(out / "orbit_002.png")[..., :3].astype(np.float64)
    assert np.abs(frames[2].astype(np.float64) - png).mean() < 8.0
    assert "orbit.mp4 (5 frames at 10 fps)" in capsys.readouterr().out


def test_video_needs_an_orbit_and_a_positive_fps(run_dir, capsys):
    assert render_main(["--model", str(run_dir), "--video"]) == 2
    assert "--video needs --orbit" in capsys.readouterr().err
    assert render_main(["--model", str(run_dir), "--orbit", "2", "--video", "--fps", "0"]) == 2
    assert "--fps" in capsys.readouterr().err


def test_missing_extra_names_the_install_command(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import imageio_ffmpeg now raises ImportError
    code = render_main(["--model", str(tmp_path / "no-such-run"), "--orbit", "3", "--video"])
    assert code == 2
    err = capsys.readouterr().err
    assert "pip install 'warpgs[video]'" in err and "no-such-run" not in err  # checked before loading the run


def test_a_crash_leaves_no_half_video_and_keeps_the_old_one(tmp_path):
    path = tmp_path / "orbit.mp4"
    frame = np.linspace(0, 1, 16 * 24 * 3).reshape(16, 24, 3)
    with Mp4Writer(path, fps=5) as video:
        for _ in range(3):
            video.append(frame)
    before = path.read_bytes()
    with pytest.raises(RuntimeError, match="render failed"):
        with Mp4Writer(path, fps=5) as video:
            video.append(frame[::-1])
            raise RuntimeError("render failed")
    assert path.read_bytes() == before and len(read_frames(path)) == 3
    assert os.listdir(tmp_path) == ["orbit.mp4"]  # the temp file went too
    with pytest.raises(ValueError, match="no frames"):
        with Mp4Writer(tmp_path / "empty.mp4"):
            pass
    assert os.listdir(tmp_path) == ["orbit.mp4"]


def test_odd_sizes_are_padded_not_rescaled(tmp_path):
    frame = np.zeros((7, 9, 3))
    frame[:, :, 0] = 1.0  # red; the padding repeats the last row and column
    with Mp4Writer(tmp_path / "odd.mp4", fps=5) as video:
        video.append(frame)
        video.append(frame)
    frames = read_frames(tmp_path / "odd.mp4")
    assert len(frames) == 2 and frames[0].shape == (8, 10, 3)
    assert frames[0][..., 0].mean() > 200 and frames[0][..., 1:].mean() < 40
