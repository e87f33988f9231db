"""benchmarks/real_capture_seeds.py: warpgs and gsplat runs pair by capture and seed across files."""
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import real_capture_seeds  # noqa: E402


def _result(tmp_path, name, seed, runs, data="/data/beer"):
    payload = {"data": data, "seed": seed, "runs": [
        {"system": system, "points": [{"step": s, "psnr": p} for s, p in points.items()]}
        for system, points in runs.items()]}
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(payload))
    return str(path)


def test_systems_pair_by_seed_across_files(tmp_path, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path / "out"))
    files = [_result(tmp_path, "w1", 1, {"warpgs": {7000: 22.0, 30000: 21.0}}),
             _result(tmp_path, "g1", 1, {"gsplat": {7000: 21.5, 30000: 21.5}}),
             _result(tmp_path, "both2", 2, {"warpgs": {7000: 23.0, 30000: 20.0}, "gsplat": {7000: 23.5, 30000: 21.0}}),
             _result(tmp_path, "w3", 3, {"warpgs": {7000: 30.0}})]  # no gsplat run for seed 3: left out
    out = real_capture_seeds.main(["pooled", *files])
    by = {(s["step"]): s for s in out["summary"]}
    assert by[7000]["seeds"] == 2 and by[7000]["delta_mean"] == pytest.approx(0.0)
    assert by[30000]["delta_mean"] == pytest.approx(-0.75) and by[30000]["delta_min"] == pytest.approx(-1.0)
    assert by[30000]["warpgs_mean"] == pytest.approx(20.5)
    assert by[30000]["delta_se"] == pytest.approx(0.25)  # sd 0.354 of the deltas -0.5, -1.0 over sqrt(2)
    assert (tmp_path / "out" / "pooled.json").is_file()


def test_a_seed_given_twice_names_both_files(tmp_path, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path / "out"))
    a = _result(tmp_path, "old", 1, {"warpgs": {7000: 22.0}})
    b = _result(tmp_path, "new", 1, {"warpgs": {7000: 22.5}})
    with pytest.raises(SystemExit, match="old.json"):
        real_capture_seeds.main(["x", a, b])


def test_captures_stay_apart_and_other_loops_are_ignored(tmp_path, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path / "out"))
    files = [_result(tmp_path, "beer", 1, {"warpgs": {7000: 22.0}, "gsplat": {7000: 21.0}}),
             _result(tmp_path, "fern", 1, {"warpgs": {7000: 26.0}, "gsplat": {7000: 25.0},
                                           "gsplat loop, warpgs raster, warpgs visibility": {7000: 0.0}},
                     data="/data/fern8")]
    out = real_capture_seeds.main(["x", *files, "--marks", "7000"])
    assert {(s["capture"], s["seeds"]) for s in out["summary"]} == {("beer", 1), ("fern8", 1)}


def test_unreadable_file_is_named(tmp_path, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path / "out"))
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(SystemExit, match="bad.json"):
        real_capture_seeds.main(["x", str(bad)])


def test_against_best_scores_the_final_model_against_gsplats_peak(tmp_path, monkeypatch):
    """Issue 31's target: warpgs's final PSNR (train.steps=auto) against the best point of gsplat's curve, and
    warpgs's training seconds over gsplat's whole run's."""
    monkeypatch.setenv("OUT", str(tmp_path / "out"))

    def run(system, points, seconds, steps=None):
        final = {"psnr": points[-1][1], "train_seconds": seconds, **({"steps": steps} if steps else {})}
        return {"system": system, "points": [{"step": s, "psnr": p} for s, p in points], "final": final}

    files = []
    for capture, seed, warpgs_final, gsplat_curve in (("beer", 1, 23.0, [(3000, 23.4), (30000, 21.0)]),
                                                      ("beer", 2, 22.8, [(3000, 22.6), (30000, 21.2)]),
                                                      ("bonsai", 1, 31.0, [(7000, 29.5), (30000, 31.2)])):
        payload = {"data": f"/data/{capture}", "seed": seed,
                   "runs": [run("warpgs", [(5000, 22.0), (6000, warpgs_final)], 30.0, 6000),
                            run("gsplat", gsplat_curve, 150.0)]}
        path = tmp_path / f"{capture}{seed}.json"
        path.write_text(json.dumps(payload))
        files.append(str(path))
    out = real_capture_seeds.main(["best", *files, "--against-best"])
    by = {s["capture"]: s for s in out["summary"]}
    assert by["beer"]["delta_mean"] == pytest.approx(-0.1) and by["beer"]["seeds"] == 2
    assert by["bonsai"]["delta_mean"] == pytest.approx(-0.2) and by["bonsai"]["time_ratio_mean"] == pytest.approx(0.2)
    assert out["overall"]["worst_capture_delta"] == pytest.approx(-0.2)
    assert out["rows"][0]["gsplat_best_step"] == 3000 and out["rows"][0]["warpgs_steps"] == 6000


def test_against_best_says_which_time_ratios_are_pairs(tmp_path, monkeypatch):
    """A time ratio compares only runs of one host and GPU (or one file); files that do not say where they ran are
    not counted as pairs either."""
    monkeypatch.setenv("OUT", str(tmp_path / "out"))

    def only(system, seed, host, capture="beer"):
        final = {"psnr": 20.0, "train_seconds": 10.0 if system == "warpgs" else 40.0}
        payload = {"data": f"/data/{capture}", "seed": seed, "runs": [
            {"system": system, "points": [{"step": 1000, "psnr": 20.0}], "final": final}]}
        if host:
            payload["host"] = {"hostname": host[0], "gpu_uuid": host[1], "load_per_core": host[2]}
        path = tmp_path / f"{capture}_{system}_{seed}.json"
        path.write_text(json.dumps(payload))
        return str(path)

    files = [only("warpgs", 1, ("a", "GPU-0", 0.1)), only("gsplat", 1, ("a", "GPU-0", 0.6)),   # a pair
             only("warpgs", 2, ("b", "GPU-0", 0.1)), only("gsplat", 2, ("a", "GPU-0", 0.1)),   # other host
             only("warpgs", 3, ("a", "GPU-1", 0.1)), only("gsplat", 3, ("a", "GPU-0", 0.1)),   # other GPU
             only("warpgs", 4, None), only("gsplat", 4, ("a", "GPU-0", 0.1))]                   # not recorded
    out = real_capture_seeds.main(["pairs", *files, "--against-best"])
    pairs = {r["seed"]: r["time_pair"] for r in out["rows"]}
    assert pairs == {1: True, 2: False, 3: False, 4: None}
    assert out["rows"][0]["max_load"] == pytest.approx(0.6) and out["rows"][3]["max_load"] == pytest.approx(0.1)
    assert out["overall"]["time_ratios_not_pairs"] == 3


def test_a_run_records_where_it_ran():
    from common import run_host
    host = run_host("cpu")
    assert host["hostname"] and host["gpu"] is None and host["gpu_uuid"] is None and host["load_per_core"] >= 0


def _final_run(system, psnr, seconds=10.0):
    return {"system": system, "points": [{"step": 1000, "psnr": psnr}],
            "final": {"psnr": psnr, "train_seconds": seconds}}


BEER = "colmap at /data/beer: 71 views (34 train, 5 test), 701x1248, 4414 points"


def _write(tmp_path, name, seed, runs, scene=BEER):
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps({"data": "/data/beer", "seed": seed, "scene": scene, "runs": runs}))
    return str(path)


def test_one_system_can_be_taken_from_a_file_that_holds_both(tmp_path, monkeypatch):
    """An old pair file gives gsplat's curve to a new warpgs run of the same seed: `FILE:gsplat`; without it the
    two warpgs runs of seed 1 collide, named."""
    monkeypatch.setenv("OUT", str(tmp_path / "out"))
    old_pair = _write(tmp_path, "old_pair", 1, [_final_run("warpgs", 20.0), _final_run("gsplat", 21.0, 40.0)])
    new = _write(tmp_path, "new", 1, [_final_run("warpgs", 22.0)])
    out = real_capture_seeds.main(["x", new, old_pair + ":gsplat", "--against-best"])
    assert out["rows"][0]["delta"] == pytest.approx(1.0) and out["rows"][0]["time_pair"] is None  # no host recorded
    with pytest.raises(SystemExit, match="old_pair.json"):
        real_capture_seeds.main(["x", new, old_pair, "--against-best"])


def test_pairs_on_different_copies_of_a_capture_are_marked_and_not_pooled(tmp_path, monkeypatch):
    """The folder a capture was read from may differ between machines; its views, resolution and SfM points may
    not (a re-made SfM, another split): such a pair is listed with same_scene False and left out of the summary."""
    monkeypatch.setenv("OUT", str(tmp_path / "out"))
    files = [_write(tmp_path, "w1", 1, [_final_run("warpgs", 22.0)]),
             _write(tmp_path, "g1", 1, [_final_run("gsplat", 21.0)],
                    scene="colmap at /tmp/elsewhere/beer: 71 views (34 train, 5 test), 701x1248, 4414 points"),
             _write(tmp_path, "w2", 2, [_final_run("warpgs", 22.0)]),
             _write(tmp_path, "g2", 2, [_final_run("gsplat", 25.0)],
                    scene="llff (images) at /data/beer: 71 views (34 train, 5 test), 720x1280, 4414 points")]
    out = real_capture_seeds.main(["x", *files, "--against-best"])
    assert [r["same_scene"] for r in out["rows"]] == [True, False]
    assert out["summary"][0]["seeds"] == 1 and out["summary"][0]["delta_mean"] == pytest.approx(1.0)
    marks = real_capture_seeds.main(["y", *files, "--marks", "1000"])
    assert len(marks["rows"]) == 2 and marks["summary"][0]["seeds"] == 1
