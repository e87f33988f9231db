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
