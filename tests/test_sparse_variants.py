"""benchmarks/sparse_variants.py: sparse.py waves that differ by an override, side by side and paired by seed."""
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import sparse_variants  # noqa: E402


def _write(folder: Path, setting: str, scene: str, seed: int, psnr: float, **extra) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    run = {"setting": setting, "scene": scene, "seed": seed, "psnr": psnr, "ssim": 0.5, "abs_rel": None,
           "num_primitives": 100, "protocol": "llff3", "n_train": 3, "steps": 1000, "downscale": 8,
           "size": [8, 6], "train_index": [1, 2, 3], "test_index": [0], "budget": None, **extra}
    (folder / f"llff3_{scene}_{setting}_s{seed}.json").write_text(json.dumps(run))


def test_differences_are_paired_by_seed_per_scene_and_over_scenes(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for seed, (ref, new) in enumerate([(20.0, 20.5), (21.0, 21.3), (22.0, 22.1)]):
        _write(a, "preset", "fern", seed, ref)
        _write(b, "preset", "fern", seed, new)
        _write(a, "preset", "room", seed, 10.0 + seed)
        _write(b, "preset", "room", seed, 10.0 + seed - 0.3)
        _write(a, "baseline", "fern", seed, 0.0)  # another setting in the same folder: not picked
        _write(a, "baseline", "room", seed, 0.0)
    variants = dict(sparse_variants.load_variant(s) for s in (f"old={a}:preset", f"new={b}:preset"))
    result = sparse_variants.compare(variants, ["old"])
    fern = result["scenes"]["fern"]["new"]["d_psnr_vs_old"]
    assert fern[0] == pytest.approx(0.3)  # +0.5, +0.3, +0.1: the seeds' spread is the pairs', not the scenes'
    assert fern[1] == pytest.approx(0.2 / 3 ** 0.5)
    assert result["scenes"]["room"]["new"]["d_psnr_vs_old"][0] == pytest.approx(-0.3)
    assert result["mean"]["new"]["d_psnr_vs_old"][0] == pytest.approx(0.0)
    assert result["scenes"]["room"]["new"]["abs_rel"] == (None, None)  # no depth reference: no figure


def test_runs_made_differently_are_refused_naming_the_files(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    _write(a, "preset", "fern", 0, 20.0)
    _write(b, "preset", "fern", 0, 20.0, steps=3000)
    variants = dict(sparse_variants.load_variant(s) for s in (f"x={a}:preset", f"y={b}:preset"))
    with pytest.raises(SystemExit, match="differ in 'steps'"):
        sparse_variants.compare(variants, ["x"])
    _write(b, "preset", "fern", 1, 20.0)
    with pytest.raises(SystemExit, match="same scenes and seeds"):
        sparse_variants.compare(variants | {"y": sparse_variants.load_variant(f"y={b}:preset")[1]}, ["x"])
    with pytest.raises(SystemExit, match="no run files with setting 'wo_drop'"):
        sparse_variants.load_variant(f"z={a}:wo_drop")
    with pytest.raises(SystemExit, match="LABEL=FOLDER:SETTING"):
        sparse_variants.load_variant(str(a))


def test_a_run_that_stopped_by_its_own_rule_may_differ_in_steps_only(tmp_path):
    """A train.steps=auto run ends where its rule says: its step count is its own, the rest of the set-up must agree."""
    a, b = tmp_path / "a", tmp_path / "b"
    _write(a, "preset", "fern", 0, 20.0)
    _write(b, "preset", "fern", 0, 20.4, steps=700, overrides=["train.steps=auto"])
    variants = dict(sparse_variants.load_variant(s) for s in (f"fixed={a}:preset", f"auto={b}:preset"))
    assert sparse_variants.compare(variants, ["fixed"])["scenes"]["fern"]["auto"]["d_psnr_vs_fixed"][0] == \
        pytest.approx(0.4)
    _write(b, "preset", "fern", 0, 20.4, steps=1500, overrides=["steps=AUTO"])  # ran past the fixed run's length
    variants["auto"] = sparse_variants.load_variant(f"auto={b}:preset")[1]
    with pytest.raises(SystemExit, match="differ in 'steps'"):
        sparse_variants.compare(variants, ["fixed"])
    _write(b, "preset", "fern", 0, 20.4, steps=700, n_train=4, overrides=["train.steps=auto"])
    variants["auto"] = sparse_variants.load_variant(f"auto={b}:preset")[1]
    with pytest.raises(SystemExit, match="differ in 'n_train'"):
        sparse_variants.compare(variants, ["fixed"])


def test_a_label_given_twice_gathers_both_folders_and_refuses_a_run_twice(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path))  # the table goes there, not into benchmarks/results
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    _write(a, "preset", "fern", 0, 20.0, overrides=["data.path=fern", "train.drop_rate=0.1"])
    _write(b, "preset", "room", 0, 10.0, overrides=["data.path=room", "train.drop_rate=0.1"])
    _write(c, "preset", "fern", 0, 21.0, overrides=["data.path=fern", "train.drop_rate=0.3"])
    _write(c, "preset", "room", 0, 10.5, overrides=["data.path=room", "train.drop_rate=0.3"])
    sparse_variants.main(["out", "--ref", "old", f"old={a}:preset", f"old={b}:preset", f"new={c}:preset"])
    out = capsys.readouterr().out
    assert "| mean | 15.00 | 15.75 | +0.75 |" in out
    assert "| old | 0.500 | n/a | 100 |" in out  # the other scores' table (the runs carry no depth reference)
    written = json.loads((tmp_path / "out.json").read_text())
    assert written["overrides"] == {"old": ["train.drop_rate=0.1"], "new": ["train.drop_rate=0.3"]}
    with pytest.raises(SystemExit, match="are both fern, seed 0"):
        sparse_variants.main(["out", "--ref", "old", f"old={a}:preset", f"old={a}:preset", f"new={c}:preset"])
