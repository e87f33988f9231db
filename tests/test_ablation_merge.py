"""benchmarks/ablation_merge.py: per-process ablation files pool into one table with the paired PSNR gain."""
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import ablation_merge  # noqa: E402


def _run(seed, psnr):
    return {"seed": seed, "psnr": psnr, "ssim": 0.5, "lpips": None, "depth_order": 0.8, "abs_rel": 0.1,
            "coverage": 0.9, "num_primitives": 100, "train_seconds": 1.0}


def _file(tmp_path, name, key, label, runs, steps=10_000, scene="/data/horns"):
    payload = {"steps": steps, "seeds": [r["seed"] for r in runs], "device": "cuda", "budget": None,
               "data": {"scene": scene, "train_index": [1, 30, 61], "test_index": [0, 8], "size": [504, 378]},
               "settings": {key: {"label": label, "preset": "p", "overrides": [], "marr": {}, "runs": runs}}}
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(payload))
    return str(path)


def test_runs_pool_over_files_and_the_gain_is_paired_by_seed(tmp_path, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path / "out"))
    (tmp_path / "out").mkdir()
    files = [_file(tmp_path, "full0", "full", "Ours (full)", [_run(0, 17.0)]),
             _file(tmp_path, "base0", "baseline", "3DGS", [_run(0, 16.0)]),
             _file(tmp_path, "base1", "baseline", "3DGS", [_run(1, 15.0)]),
             _file(tmp_path, "full1", "full", "Ours (full)", [_run(1, 17.0)])]
    merged = ablation_merge.main(["merged", *files])
    assert list(merged["settings"]) == ["baseline", "full"]  # baseline first, whatever the file order
    assert merged["seeds"] == [0, 1]
    full = merged["settings"]["full"]["mean"]
    assert full["psnr"] == pytest.approx(17.0)
    assert full["psnr_vs_baseline"] == pytest.approx(1.5)  # (17-16 + 17-15) / 2, paired by seed
    written = json.loads((tmp_path / "out" / "merged.json").read_text())
    assert written["table"][1]["Δ PSNR vs 3DGS"].startswith("1.50")


def test_files_of_different_scenes_or_steps_or_a_repeated_seed_are_refused(tmp_path):
    a = _file(tmp_path, "a", "full", "Ours (full)", [_run(0, 17.0)])
    with pytest.raises(SystemExit, match="steps"):
        ablation_merge.main(["m", a, _file(tmp_path, "b", "full", "Ours (full)", [_run(1, 17.0)], steps=300)])
    with pytest.raises(SystemExit, match="scene"):
        ablation_merge.main(["m", a, _file(tmp_path, "c", "full", "Ours (full)", [_run(1, 17.0)], scene="/x")])
    with pytest.raises(SystemExit, match="seed 0"):
        ablation_merge.main(["m", a, _file(tmp_path, "d", "full", "Ours (full)", [_run(0, 17.5)])])
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(SystemExit, match="bad.json"):
        ablation_merge.main(["m", a, str(tmp_path / "bad.json")])


def test_the_parallel_runner_checks_its_arguments():
    import ablation_jobs

    args, rest, keys, seeds = ablation_jobs.parse(["--name", "n", "--only", "baseline,full", "--seeds", "0,2", "--",
                                                   "--data", "d", "--device", "cuda"])
    assert rest == ["--data", "d", "--device", "cuda"] and keys == ["baseline", "full"] and seeds == [0, 2]
    _, _, every, _ = ablation_jobs.parse(["--name", "n", "--", "--data", "d"])
    assert every[0] == "baseline" and "wo_confidence" in every  # the real settings when --data is given
    with pytest.raises(SystemExit, match="--seeds"):
        ablation_jobs.parse(["--name", "n", "--", "--data", "d", "--seeds", "1"])
    with pytest.raises(SystemExit, match="not settings"):
        ablation_jobs.parse(["--name", "n", "--only", "full,wo_magic"])
