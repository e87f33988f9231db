"""data.exclude: views left out by image name or glob, the split otherwise kept, and a pattern that matches nothing
named as an error."""
import pytest

from train_fixtures import quick_overrides, small_orbit
from warpgs.config.loader import load_config
from warpgs.data import load_scene
from warpgs.data.exclude import excluding
from warpgs.train.trainer import Trainer


@pytest.fixture(scope="module")
def orbit():
    return load_scene(small_orbit(), split="llff")  # 16 views; test 0 and 8


def names(scene, indices):
    return [scene.native_cameras[i].name for i in indices]


def test_names_and_globs_leave_views_out_and_keep_the_rest_of_the_split(orbit):
    out = excluding(orbit, ["orbit_003.png", "orbit_01[0-2].png", "orbit_008.png"])
    assert names(out, out.train) == [n for n in names(orbit, orbit.train)
                                     if n not in ("orbit_003.png", "orbit_010.png", "orbit_011.png", "orbit_012.png")]
    assert names(out, out.test) == ["orbit_000.png"]
    assert out.metadata["excluded"] == ["orbit_003.png", "orbit_008.png", "orbit_010.png", "orbit_011.png",
                                        "orbit_012.png"]
    assert "10 train, 1 test, 5 left out" in out.summary()
    assert orbit.train == [1, 2, 3, 4, 5, 6, 7, 9, 10, 11, 12, 13, 14, 15]  # the original is untouched
    assert excluding(orbit, []) is orbit


def test_a_range_of_names_in_natural_order_both_ends_included(orbit):
    out = excluding(orbit, ["orbit_002.png..orbit_004.png", "orbit_015.png..orbit_015.png"])
    assert out.metadata["excluded"] == ["orbit_002.png", "orbit_003.png", "orbit_004.png", "orbit_015.png"]
    with pytest.raises(ValueError, match=r"'orbit_02.png' is not a view of the scene .*'orbit_000.png'..'orbit_015.png'"):
        excluding(orbit, ["orbit_000.png..orbit_02.png"])
    with pytest.raises(ValueError, match="'orbit_009.png' comes after 'orbit_004.png' in name order"):
        excluding(orbit, ["orbit_009.png..orbit_004.png"])


def test_a_pattern_that_matches_no_view_is_named(orbit):
    with pytest.raises(ValueError, match=r"data.exclude: 'frame_0014.png' matches no view of the scene at .*orbit64 "
                                         r"\(its views are named like 'orbit_000.png'\)"):
        excluding(orbit, ["orbit_001.png", "frame_0014.png"])
    with pytest.raises(ValueError, match="data.exclude: expected image names, globs or FIRST..LAST"):
        excluding(orbit, [""])


def test_config_takes_one_name_or_a_list(tmp_path):
    assert load_config(None, ["data.exclude=orbit_003.png"]).data.exclude == ["orbit_003.png"]
    assert load_config(None, ["data.exclude=[orbit_003.png, 'orbit_01?.png']"]).data.exclude == [
        "orbit_003.png", "orbit_01?.png"]
    # YAML cannot read a flow list with a bare '?' (a key marker to it): taken apart at the commas instead
    assert load_config(None, ["data.exclude=[orbit_00?.png, 00[2-3]?.jpg]"]).data.exclude == [
        "orbit_00?.png", "00[2-3]?.jpg"]
    assert load_config(None, []).data.exclude == []


def test_trainer_trains_and_scores_without_the_left_out_views(tmp_path):
    trainer = Trainer(None, overrides=quick_overrides(tmp_path, steps=1) + ["data.exclude=[orbit_00?.png]"],
                      quiet=True)
    assert names(trainer.scene, trainer.scene.train) == [f"orbit_{i:03d}.png" for i in (10, 11, 12, 13, 14, 15)]
    assert trainer.scene.test == []  # both test views (0 and 8) were among them: evaluation falls back to train
    with pytest.raises(ValueError, match="no training views after data.exclude"):
        Trainer(None, overrides=quick_overrides(tmp_path, steps=1) + ["data.exclude=['orbit_*']"], quiet=True)


def test_a_range_follows_natural_order_for_unpadded_names():
    from types import SimpleNamespace

    class Frames(SimpleNamespace):
        def with_split(self, train, test):
            return Frames(native_cameras=self.native_cameras, root=self.root, train=list(train), test=list(test),
                          metadata={})

    names = [f"frame_{i}.png" for i in (0, 1, 2, 9, 10, 11, 20)]  # lexically frame_10 < frame_2
    scene = Frames(native_cameras=[SimpleNamespace(name=n) for n in names], root="video", train=list(range(7)),
                   test=[], metadata={})
    assert excluding(scene, ["frame_2.png..frame_11.png"]).metadata["excluded"] == [
        "frame_2.png", "frame_9.png", "frame_10.png", "frame_11.png"]
