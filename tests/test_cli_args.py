"""warpgs-train's command line: CONFIG, options and key=value overrides in any order (issue 12: `warpgs-train
gaussians --data X steps=10` failed with "unrecognized arguments: steps=10")."""
import itertools

import pytest
import yaml

from warpgs.cli.commands import train_main


def resolved(capsys, argv):
    assert train_main(list(argv) + ["--print-config"]) == 0
    return yaml.safe_load(capsys.readouterr().out)


@pytest.mark.parametrize("order", list(itertools.permutations(range(4))))
def test_preset_options_and_overrides_in_any_order(capsys, tmp_path, order):
    parts = [["gaussians"], ["--data", str(tmp_path / "scene")], ["steps=10"], ["--out", str(tmp_path / "out")]]
    cfg = resolved(capsys, [a for i in order for a in parts[i]])
    assert cfg["data"]["path"] == str(tmp_path / "scene")
    assert cfg["output"]["dir"] == str(tmp_path / "out")
    assert cfg["train"]["steps"] == 10
    assert cfg["strategy"]["reset_every"] == 3000  # the gaussians preset, not default.yaml (reset_every 0)


def test_overrides_split_by_an_option_all_apply(capsys, tmp_path):
    cfg = resolved(capsys, ["steps=7", "--data", str(tmp_path), "gaussians", "seed=3", "--quiet", "optim.quats_lr=0.002"])
    assert (cfg["train"]["steps"], cfg["train"]["seed"], cfg["optim"]["quats_lr"]) == (7, 3, 0.002)
    assert cfg["data"]["path"] == str(tmp_path)


def test_two_configs_are_still_refused(capsys):
    with pytest.raises(SystemExit, match="more than one CONFIG"):
        train_main(["gaussians", "--quiet", "surfels", "--print-config"])


def test_unknown_option_is_still_an_error(capsys):
    with pytest.raises(SystemExit) as e:
        train_main(["gaussians", "--dta", "x", "--print-config"])
    assert e.value.code == 2 and "--dta" in capsys.readouterr().err


def test_data_without_a_preset_trains_with_the_gaussians_recipe(capsys, tmp_path):
    # Issue 34: the demo preset is for the built-in scene; a user's scene gets the real-capture recipe.
    cfg = resolved(capsys, ["--data", str(tmp_path)])
    assert cfg["data"]["path"] == str(tmp_path)
    assert (cfg["train"]["steps"], cfg["strategy"]["reset_every"]) == ("auto", 3000)  # the gaussians preset
    assert resolved(capsys, [f"data.path={tmp_path}"])["train"]["steps"] == "auto"
    assert resolved(capsys, ["data.path=null"])["train"]["steps"] == 1000  # the built-in scene after all
    demo = resolved(capsys, [])
    assert (demo["data"]["path"], demo["train"]["steps"], demo["strategy"]["reset_every"]) == (None, 1000, 0)
    assert resolved(capsys, ["default", "--data", str(tmp_path)])["train"]["steps"] == 1000  # named: as asked


def test_help_says_which_preset_data_gets(capsys):
    with pytest.raises(SystemExit):
        train_main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "With --data and no CONFIG the preset is 'gaussians'" in text


def test_a_video_as_data_trains_on_the_scene_folder_beside_it(capsys, tmp_path):
    cfg = resolved(capsys, ["--data", str(tmp_path / "clip.mp4")])
    assert cfg["data"]["path"] == str(tmp_path / "clip") and cfg["train"]["steps"] == "auto"
    bad = tmp_path / "bad.mov"
    bad.write_bytes(b"no video")
    pytest.importorskip("imageio_ffmpeg")
    assert train_main(["--data", str(bad), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "warpgs-train: error:" in err and "bad.mov: not a readable video" in err


def test_nproc_is_checked_and_one_process_needs_no_launcher(capsys):
    from warpgs.cli.launch import check_nproc

    with pytest.raises(ValueError, match="--nproc: expected a positive number"):
        check_nproc(0)
    check_nproc(1)
    assert train_main(["--nproc", "0", "steps=1"]) == 2
    assert "--nproc: expected a positive number of processes, got 0" in capsys.readouterr().err
