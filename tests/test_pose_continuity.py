"""warpgs.data.pose_checks: a video's poses move smoothly; a frame put on the wrong side shows as jumps."""
import numpy as np
import pytest

from warpgs.data.camera import Camera, look_at
from warpgs.data.pose_checks import continuity, video_pose_jumps

K = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])


def orbit_frames(n=24, flipped=()):
    """Frames of a slow orbit named frame_0 ... frame_23; `flipped` ones are placed half a turn away."""
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / 48 + (np.pi if i in flipped else 0.0)
        cams.append(Camera(K, look_at((4 * np.cos(a), 4 * np.sin(a), 1.0), (0, 0, 0)), 80, 60, name=f"frame_{i}.png"))
    return cams[::-1]  # any order in: they are sorted by name, frame_2 before frame_10


def test_a_smooth_orbit_has_no_jumps_and_a_flipped_frame_gives_two():
    smooth = continuity(orbit_frames())
    assert smooth["frames"] == 24 and smooth["jumps"] == [] and 7.0 < smooth["median_turn_deg"] < 8.0
    found = continuity(orbit_frames(flipped={10}))
    assert [(j["from"], j["to"]) for j in found["jumps"]] == [("frame_9.png", "frame_10.png"),
                                                                ("frame_10.png", "frame_11.png")]
    assert all(j["turn_deg"] > 150 for j in found["jumps"])


def test_only_a_video_like_set_is_judged():
    assert [j["to"] for j in video_pose_jumps(orbit_frames(flipped={10}))] == ["frame_10.png", "frame_11.png"]
    assert video_pose_jumps(orbit_frames()) == []
    rng = np.random.default_rng(0)  # a photo collection: names say nothing about where the photos were taken
    shuffled = orbit_frames()
    names = rng.permutation([c.name for c in shuffled])
    collection = [Camera(K, c.viewmat, 80, 60, name=n) for c, n in zip(shuffled, names)]
    assert len(continuity(collection)["jumps"]) > 0 and video_pose_jumps(collection) == []
    with pytest.raises(ValueError, match="3 frames"):
        continuity(orbit_frames()[:2])


def scene_of(frames, left_out=()):
    from types import SimpleNamespace

    used = [i for i, cam in enumerate(frames) if cam.name not in {f"frame_{k}.png" for k in left_out}]
    return SimpleNamespace(native_cameras=frames, root="scene", train=used[1:], test=used[:1])


def test_training_warns_about_a_video_whose_poses_jump(capsys):
    from warpgs.train.setup import warn_pose_jumps

    assert warn_pose_jumps(scene_of(orbit_frames())) == []
    assert capsys.readouterr().err == ""
    assert len(warn_pose_jumps(scene_of(orbit_frames(flipped={4, 5})))) == 2
    err = capsys.readouterr().err
    assert "scene" in err and "frame_3.png -> frame_4.png" in err and "frame_5.png -> frame_6.png" in err
    assert "data.exclude" in err  # and says how to leave such frames out


def test_no_warning_once_the_flipped_frames_are_left_out(capsys):
    from warpgs.train.setup import warn_pose_jumps

    assert warn_pose_jumps(scene_of(orbit_frames(flipped={4, 5}), left_out={4, 5})) == []
    assert capsys.readouterr().err == ""
    assert len(warn_pose_jumps(scene_of(orbit_frames(flipped={4, 5}), left_out={4}))) == 1  # 5 -> 6 is still used


def test_the_warning_comes_once_per_training_run_not_when_a_trainer_is_only_built(tmp_path, monkeypatch):
    """Render, eval and the viewer build Trainers too; a resumed run was warned when it started."""
    from train_fixtures import quick_overrides
    from warpgs.train import setup as train_setup
    from warpgs.train.trainer import Trainer

    warned = []
    monkeypatch.setattr(train_setup, "warn_pose_jumps", lambda scene, say=None: warned.append(scene.root) or [])
    trainer = Trainer(None, overrides=quick_overrides(tmp_path, steps=2))
    assert warned == []
    trainer.fit()
    assert len(warned) == 1
    resumed = Trainer(None, overrides=quick_overrides(tmp_path, steps=4), resume=True)
    assert resumed.step == 2
    resumed.fit()
    assert len(warned) == 1


def test_a_video_folded_in_half_splits_into_two_sides_and_the_warning_names_the_smaller(capsys):
    from warpgs.data.pose_checks import folded_halves
    from warpgs.train.setup import warn_pose_jumps

    folded = orbit_frames(flipped=set(range(4, 10)))  # frames 4-9 half a turn around: two half-turn jumps
    assert folded_halves(folded) == [[("frame_0.png", "frame_3.png", 4), ("frame_10.png", "frame_23.png", 14)],
                                     [("frame_4.png", "frame_9.png", 6)]]
    assert folded_halves(orbit_frames()) == []
    quarter = [Camera(K, look_at((4 * np.cos(a), 4 * np.sin(a), 1.0), (0, 0, 0)), 80, 60, name=f"frame_{i}.png")
               for i, a in enumerate(2 * np.pi * i / 48 + (np.pi / 2 if i >= 12 else 0.0) for i in range(24))]
    assert len(video_pose_jumps(quarter)) == 1 and folded_halves(quarter) == []  # a 90-degree jump: no fold
    warn_pose_jumps(scene_of(folded))
    err = capsys.readouterr().err
    assert "frame_0.png..frame_3.png, frame_10.png..frame_23.png (18 frames)" in err
    assert "Train on the larger with data.exclude=[frame_4.png..frame_9.png]" in err
