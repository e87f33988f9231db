"""benchmarks/sparse.py (issue 30): the plan, the protocol's split, resuming, the tables' statistics; and
benchmarks/sparse_data.py's trimmed LLFF copy with its reference depth."""
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from data_fixtures import synthetic_dir
from test_sparse_llff import _cameras, _llff_with_model, _tracked_points, fsgs_split
from warpgs.data import load_scene
from warpgs.data.depth.reference_points import sparse_depth_map, view_reference_points

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))

import sparse  # noqa: E402
import sparse_along  # noqa: E402
import sparse_data  # noqa: E402
import sparse_runs  # noqa: E402
import sparse_tables  # noqa: E402


def _runs(out: Path) -> dict:
    return {p.name: p.stat().st_mtime_ns for p in (out / "runs").glob("*.json")}


def test_a_wave_writes_a_file_a_run_resumes_and_tabulates(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path))  # the table's JSON, not into benchmarks/results
    scene = synthetic_dir("orbit")  # 36 views at 128x96: 24 train under the 360 protocol, 5 test (0, 8, ...)
    out = tmp_path / "out"
    common = ["--protocol", "m360_24", "--scenes", str(scene), "--settings", "baseline", "--seeds", "3",
              "--steps", "8", "--budget", "1000", "--threads", "1", "--out", str(out), "--marr", "alpha_min=0.2",
              "eval.every=4"]
    sparse.main(common + ["--dry-run"])
    listed = capsys.readouterr().out
    assert "1 runs (0 done, 1 to do)" in listed and "m360_24_orbit_baseline_s3" in listed
    payload = sparse.main(common + ["--name", "t_orbit"])
    assert json.loads((tmp_path / "sparse_t_orbit.json").read_text())["summary"] == json.loads(json.dumps(
        payload["summary"]))
    assert set(_runs(out)) == {"m360_24_orbit_baseline_s3.json"}
    run = json.loads((out / "runs" / "m360_24_orbit_baseline_s3.json").read_text())
    want_train, want_test = fsgs_split(36, 24)
    assert run["train_index"] == want_train and run["test_index"] == want_test
    assert (run["steps"], run["seed"], run["budget"]) == (8, 3, 1000)
    assert run["marr"] == {"alpha_min": 0.2}  # --marr reached the worker
    assert math.isfinite(run["psnr"]) and run["abs_rel"] is not None  # the synthetic scene carries exact depth
    assert payload["summary"]["scenes"]["orbit"]["baseline"]["psnr"] == (run["psnr"], None)
    assert [h["step"] for h in run["history"]] == [4]  # the periodic test evaluation the override asked for
    assert "--worker run" in run["command"] and run["command"].endswith("eval.every=4")  # the worker's own
    assert "eval.every=4" in payload["command"] and "--name t_orbit" in payload["command"]
    assert "--worker run" in payload["runs"][0]["command"] and "--seed 3" in payload["runs"][0]["command"]
    # A second call finds every run done: nothing trains again, the table is made from the files.
    before = _runs(out)
    sparse.main(common + ["--name", "t_orbit"])
    assert _runs(out) == before
    sparse.main(common + ["--dry-run"])
    assert "1 runs (1 done, 0 to do)" in capsys.readouterr().out
    # --at-step: the tables of the scores the history has at that step (depth is scored at the end only).
    early = sparse.main(common + ["--name", "t_orbit_4", "--table", "--at-step", "4"])
    row = early["summary"]["scenes"]["orbit"]["baseline"]
    assert row["psnr"] == (run["history"][0]["psnr"], None) and row["abs_rel"] == (None, None)
    assert "scored at step 4" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="no score at that step"):
        sparse.main(common + ["--name", "t_orbit_5", "--table", "--at-step", "5"])
    last = sparse.main(common + ["--name", "t_orbit_8", "--table", "--at-step", "8"])  # the run's end: its final scores
    assert last["summary"]["scenes"]["orbit"]["baseline"]["psnr"] == (run["psnr"], None)
    # --along: the scores at every scored step, the final one included, one table
    along = sparse.main(common + ["--name", "t_orbit_along", "--table", "--along"])["along"]
    assert along == {"orbit": {"baseline": {4: (run["history"][0]["psnr"], None), 8: (run["psnr"], None)}}}
    assert "| orbit | 3DGS | " in capsys.readouterr().out
    with pytest.raises(SystemExit, match="--along: only with --table"):
        sparse.main(common + ["--along"])
    with pytest.raises(SystemExit, match="only with --table"):
        sparse.main(common + ["--at-step", "4"])


def test_keep_going_tabulates_the_runs_made_and_names_the_failed_one(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path))
    scene = synthetic_dir("orbit")
    out = tmp_path / "out"
    made = sparse.worker_cmd

    def failing_seed_1(args, kind, sc, run=None):  # seed 1's run cannot start, as a capture too thin for an arm
        if run is not None and run.seed == 1:
            return [sys.executable, "-c", "raise SystemExit('triangulation found only 19 points')"]
        return made(args, kind, sc, run)

    monkeypatch.setattr(sparse, "worker_cmd", failing_seed_1)
    common = ["--protocol", "m360_24", "--scenes", str(scene), "--settings", "baseline", "--seeds", "0,1",
              "--steps", "4", "--budget", "1000", "--threads", "1", "--per-gpu", "2", "--out", str(out),
              "--name", "t_keep"]
    with pytest.raises(SystemExit, match="failed"):  # by default the first failure stops the wave
        sparse.main(common)
    with pytest.raises(SystemExit, match=r"1 failed .*m360_24_orbit_baseline_s1"):
        sparse.main(common + ["--keep-going"])
    assert set(_runs(out)) == {"m360_24_orbit_baseline_s0.json"}
    table = json.loads((tmp_path / "sparse_t_keep.json").read_text())
    assert table["missing"] == ["m360_24_orbit_baseline_s1"] and len(table["runs"]) == 1
    assert "19 points" in capsys.readouterr().err


def test_keep_going_skips_the_runs_of_a_failed_prior_and_names_every_failure(tmp_path, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path))
    scene = synthetic_dir("orbit")
    made = sparse.worker_cmd
    broken = [sys.executable, "-c", "raise SystemExit('broken')"]
    common = ["--protocol", "m360_24", "--scenes", str(scene), "--seeds", "0", "--steps", "4", "--budget", "1000",
              "--threads", "1", "--per-gpu", "2", "--keep-going", "--name", "t_prior"]
    # The prior fails: 3DGS (no prior) is still made, the preset is skipped, and both are named.
    monkeypatch.setattr(sparse, "worker_cmd", lambda args, kind, sc, run=None:
                        broken if kind == "prior" else made(args, kind, sc, run))
    out = tmp_path / "a"
    with pytest.raises(SystemExit, match=r"1 failed .*prior_m360_24_orbit; skipped, their prior failed: "
                                          r"m360_24_orbit_preset_s0"):
        sparse.main(common + ["--settings", "baseline,preset", "--out", str(out)])
    assert set(_runs(out)) == {"m360_24_orbit_baseline_s0.json"}
    # Every run fails: no table can be made, and the failures are still named.
    monkeypatch.setattr(sparse, "worker_cmd", lambda args, kind, sc, run=None: broken)
    with pytest.raises(SystemExit, match=r"(?s)no run files.*1 failed .*m360_24_orbit_baseline_s0"):
        sparse.main(common + ["--settings", "baseline", "--out", str(tmp_path / "b")])


def test_a_run_file_made_with_other_steps_is_not_reused(tmp_path):
    """Run files are named without the steps, budget and downscale: resuming into the same --out with other ones
    must not count (or tabulate) the old runs as done."""
    scene = synthetic_dir("orbit")
    out = tmp_path / "out"
    (out / "runs").mkdir(parents=True)
    old = {"id": "m360_24_orbit_baseline_s0", "scene": "orbit", "setting": "baseline", "seed": 0, "steps": 8,
           "budget": 1000, "downscale": 1, "psnr": 10.0}
    (out / "runs" / "m360_24_orbit_baseline_s0.json").write_text(json.dumps(old))
    common = ["--protocol", "m360_24", "--scenes", str(scene), "--settings", "baseline", "--budget", "1000",
              "--out", str(out)]
    for extra in (["--dry-run"], ["--table"]):
        with pytest.raises(SystemExit, match="made with steps 8; this plan asks for steps 1000"):
            sparse.main(common + extra)
    with pytest.raises(SystemExit, match="made with budget 1000; this plan asks for budget 2000"):
        sparse.main(common[:-4] + ["--budget", "2000", "--steps", "8", "--out", str(out), "--dry-run"])


def test_a_run_that_stopped_by_its_own_rule_is_read_within_the_plans_steps(tmp_path):
    """train.steps=auto ends a run where its validation rule says, bounded by the plan's steps: its file counts as
    made by the plan when it stopped within them, never when it ran past them."""
    scene = synthetic_dir("orbit")
    out = tmp_path / "out"
    (out / "runs").mkdir(parents=True)
    run_file = out / "runs" / "m360_24_orbit_baseline_s0.json"
    common = ["--protocol", "m360_24", "--scenes", str(scene), "--settings", "baseline", "--budget", "1000",
              "--steps", "10", "--out", str(out), "--dry-run", "train.steps=auto"]
    for steps, plan, reused in ((8, common, True), (8, common[:-1] + ["steps=AUTO"], True), (8, common[:-1], False),
                                (12, common, False)):
        run = {"id": "m360_24_orbit_baseline_s0", "scene": "orbit", "setting": "baseline", "seed": 0, "steps": steps,
               "budget": 1000, "downscale": 1, "psnr": 10.0, "overrides": ["train.steps=auto"]}
        run_file.write_text(json.dumps(run))
        if reused:
            sparse.main(plan)
        else:  # run past the bound, or a plan of fixed length: not this plan's run
            with pytest.raises(SystemExit, match=f"made with steps {steps}; this plan asks for steps 10"):
                sparse.main(plan)


def test_a_prior_made_at_another_downscale_is_not_reused(tmp_path):
    scene = synthetic_dir("orbit")
    out = tmp_path / "out"
    folder = out / "priors" / "m360_24_orbit"
    folder.mkdir(parents=True)
    (folder / "prior.json").write_text(json.dumps({"downscale": 2}))
    common = ["--protocol", "m360_24", "--scenes", str(scene), "--settings", "full", "--out", str(out), "--dry-run"]
    with pytest.raises(SystemExit, match="made at downscale 2, this plan reads orbit at 1"):
        sparse.main(common)
    (folder / "prior.json").write_text(json.dumps({"downscale": 1}))
    sparse.main(common)  # the same downscale: done


def _result(scene, setting, seed, psnr):
    return {"scene": scene, "setting": setting, "seed": seed, "psnr": psnr, "ssim": 0.5, "lpips": None,
            "depth_order": None, "abs_rel": None, "coverage": None, "num_primitives": 10, "train_seconds": 1.0}


def test_tables_pair_seeds_and_average_scenes(capsys):
    results = [_result("a", "baseline", 0, 15.0), _result("a", "baseline", 1, 16.0),
               _result("a", "full", 0, 17.0), _result("a", "full", 1, 19.0),
               _result("a", "wo_depth", 0, 16.0), _result("a", "wo_depth", 1, 18.0),
               _result("b", "baseline", 0, 20.0), _result("b", "full", 0, 21.0)]
    summary = sparse_tables.summarise(results, ["baseline", "wo_depth", "full"])
    a = summary["scenes"]["a"]
    assert a["full"]["psnr"] == pytest.approx((18.0, 1.0))  # mean, stdev / sqrt(2)
    assert a["full"]["d_psnr_vs_baseline"] == pytest.approx((2.5, 0.5))  # paired: +2, +3
    assert a["wo_depth"]["d_psnr_vs_full"] == pytest.approx((-1.0, 0.0))
    assert summary["scenes"]["b"]["full"]["psnr"] == (21.0, None)  # one seed: no standard error
    mean = summary["mean"]
    assert mean["full"]["psnr"][0] == pytest.approx((18.0 + 21.0) / 2)
    assert mean["full"]["psnr"][1] is None  # scene b has a single seed
    assert mean["wo_depth"]["scenes"] == 1
    sparse_tables.print_tables(summary, "header")
    printed = capsys.readouterr().out
    # The paper's rows beside ours: w/o DR (the depth term) is 0.32 dB under the paper's full method, ours -1.00.
    assert "| w/o DR | 21.79 | -0.32 | 0.722 | 0.228 | 17.00 ± 1.00 | -1.00 ± 0.00 |" in printed
    assert "| w/o DGR | 22.00 | -0.11 | 0.728 | 0.222 | not run |" in printed
    assert "worst view PSNR" not in printed  # no run has per-view scores


def test_tables_show_the_worst_test_view():
    """A view a floater covers (figurine's 8.5 dB beside a 14.5 dB mean) shows in its own column; a run scored at an
    earlier step has no per-view scores at that step, so it gives none."""
    runs = [{**_result("a", "baseline", s, 15.0), "per_view": {"v0": {"psnr": 18.0}, "v1": {"psnr": w}}}
            for s, w in ((0, 9.0), (1, 11.0))]
    row = sparse_tables.summarise(runs, ["baseline"])["scenes"]["a"]["baseline"]
    assert row["worst_view_psnr"] == pytest.approx((10.0, 1.0))
    early = [{**r, "scored_at_step": 1000} for r in runs]
    assert sparse_tables.summarise(early, ["baseline"])["scenes"]["a"]["baseline"]["worst_view_psnr"] == (None, None)


def test_the_light_field_protocol_trains_on_the_3x3_grid(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path))
    scene = synthetic_dir("lightfield")  # a 3x3 array plus off-grid views
    out = tmp_path / "out"
    common = ["--protocol", "lf3x3", "--scenes", f"{scene}@1", "--settings", "baseline", "--steps", "4", "--budget",
              "1000", "--threads", "1", "--out", str(out)]
    sparse.main(common + ["--name", "t_lf"])
    run = json.loads((out / "runs" / f"lf3x3_{scene.name}_baseline_s0.json").read_text())
    grid = load_scene(scene)  # the light field's own grid protocol
    assert run["train_index"] == grid.train and run["test_index"] == grid.test and len(run["train"]) == 9
    assert "data.split=grid" in run["overrides"] and "data.n_train=null" in run["overrides"]
    assert math.isfinite(run["psnr"])
    assert sparse_runs.PROTOCOLS["llff3"].data_overrides() == ["data.split=llff", "data.n_train=3"]
    with pytest.raises(SystemExit, match="3x3 grid"):
        sparse.main(common + ["--n-train", "4", "--dry-run"])


def test_settings_groups_and_bad_input():
    assert sparse_runs.expand_settings("main") == ["baseline", "preset", "full"]
    assert sparse_runs.expand_settings("paper")[1:-1] == [f"wo_{t}" for t in ("depth", "depth_grad", "depth_local",
                                                                          "opacity", "scale", "count")]
    assert set(sparse_tables.PAPER_TABLE2) == set(sparse_runs.expand_settings("paper"))
    with pytest.raises(SystemExit, match="--settings: 'wo_nothing'"):
        sparse_runs.expand_settings("baseline,wo_nothing")
    with pytest.raises(SystemExit, match="is not a folder"):
        sparse.main(["--scenes", "/no/such/scene", "--dry-run"])


def test_a_dry_run_does_not_reconstruct_a_folder_of_images(tmp_path, capsys):
    """A capture without poses is listed as such; its SfM is left to the first run (no database written)."""
    from PIL import Image

    scene = tmp_path / "photos"
    (scene / "images").mkdir(parents=True)
    for i in range(4):
        Image.new("RGB", (32, 24), (40 * i, 80, 120)).save(scene / "images" / f"{i:03d}.jpg")
    sparse.main(["--protocol", "m360_24", "--scenes", str(scene), "--settings", "baseline", "--seeds", "0",
                 "--out", str(tmp_path / "out"), "--dry-run"])
    listed = capsys.readouterr().out
    assert "the first run makes the poses with SfM" in listed and "m360_24_photos_baseline_s0" in listed
    assert not (scene / "database.db").exists() and not (scene / "sparse").exists()


def test_trimmed_llff_copy_keeps_split_cameras_and_reference(tmp_path):
    cams = _cameras(n=12)
    points = _tracked_points(cams)
    src = _llff_with_model(tmp_path / "src", cams, points, images_bin=False)  # ids from the LLFF bounds
    out = sparse_data.prepare_llff(src, tmp_path / "out", factor=2, jpeg_quality=98)
    assert not (out / "images").exists() and not (out / "sparse").exists()
    assert len(list((out / "images_2").glob("*.jpg"))) == 12
    full = load_scene(src, split="llff", n_train=3, downscale=2)
    trimmed = load_scene(out, split="llff", n_train=3, downscale=2)
    assert (trimmed.train, trimmed.test) == (full.train, full.test) == fsgs_split(12, 3)
    for a, b in zip(full.cameras, trimmed.cameras):
        assert (a.width, a.height) == (b.width, b.height)
        np.testing.assert_allclose(a.K, b.K)
        np.testing.assert_allclose(a.viewmat, b.viewmat)
    # The reference depth read back is the one made from the model at the served resolution.
    ref, per_view = view_reference_points(full)
    names = [trimmed.names[v] for v in trimmed.test]
    got = sparse_data.read_reference_depth(out, names, trimmed.cameras[0].width, trimmed.cameras[0].height)
    for v, name in zip(trimmed.test, names):
        want = sparse_depth_map(full.cameras[v], ref.xyz[per_view[v]])
        assert (want > 0).sum() > 0
        np.testing.assert_allclose(got[name], want, rtol=1e-6)
    with pytest.raises(SystemExit, match="made at"):
        sparse_data.read_reference_depth(out, names, 10, 10)
    # With the full-size images kept instead, they are the native ones (what triangulation reads), served at 1/2.
    kept_dir = sparse_data.prepare_llff(src, tmp_path / "kept", factor=2, keep_images=True)
    kept = load_scene(kept_dir, downscale=2)
    assert (kept.native_cameras[0].width, kept.cameras[0].width) == (64, 32)
    assert not (kept_dir / "images_2").exists() and (kept_dir / sparse_data.REFERENCE_FILE).is_file()


def test_prior_accuracy_scores_a_waves_priors_at_the_training_views(tmp_path, monkeypatch, capsys):
    import sparse_prior_accuracy
    from warpgs.data.depth.priors import write_prior

    monkeypatch.setenv("OUT", str(tmp_path))
    cams = _cameras(n=12)
    src = _llff_with_model(tmp_path / "src", cams, _tracked_points(cams), images_bin=False)
    scene_dir = sparse_data.prepare_llff(src, tmp_path / "scene", factor=2, jpeg_quality=98)
    scene = load_scene(scene_dir, split="llff", n_train=3, downscale=2)
    w, h = scene.cameras[0].width, scene.cameras[0].height
    folder = tmp_path / "out" / "priors" / f"llff3_{scene_dir.name}"
    args = ["--out", str(tmp_path / "out"), "--scenes", f"{scene_dir}@2", "--name", "t"]
    with pytest.raises(SystemExit, match="no prior"):
        sparse_prior_accuracy.main(args)
    names = [scene.names[v] for v in scene.train]
    reference = sparse_data.read_reference_depth(scene_dir, names, w, h)
    for name in names:  # 10% too far at every reference point; confident on the left half only
        z = reference[name]
        inv = np.where(z > 0, 1.0 / (1.1 * np.where(z > 0, z, 1.0)), 0.5).astype(np.float32)
        conf = np.zeros((h, w), np.float32)
        conf[:, : w // 2] = 1.0
        write_prior(folder / f"{Path(name).stem}.exr", inv, np.ones((h, w), bool), conf)
    (folder / "prior.json").write_text("{}")
    payload = sparse_prior_accuracy.main(args)
    mean = payload["scenes"][scene_dir.name]["mean"]
    assert mean["abs_rel"] == pytest.approx(0.1, rel=1e-4)  # |1.1 z - z| / z
    assert mean["delta1"] == 1.0 and mean["point_coverage"] == 1.0 and mean["valid_pixels"] == 1.0
    assert mean["confident_pixels"] == pytest.approx((w // 2) / w)
    assert mean["abs_rel_confidence4_weighted"] == pytest.approx(0.1, rel=1e-4)  # the same error everywhere
    assert "scale_error" not in mean  # no format.json: no alignment recorded
    assert json.loads((tmp_path / "sparse_prior_accuracy_t.json").read_text())["scenes"].keys() == {scene_dir.name}
    # The worst view's alignment scale, as compute_depth_priors records it in format.json.
    scales = [1.01, 0.96, 1.0]
    (folder / "format.json").write_text(json.dumps({"views": {n: {"alignment": {"scale": c}}
                                                              for n, c in zip(names, scales)}}))
    mean = sparse_prior_accuracy.main(args)["scenes"][scene_dir.name]["mean"]
    assert mean["scale_error"] == pytest.approx(0.04) and mean["unaligned_views"] == 0
    # A view kept unaligned (its valid pixels met too few SfM points) is counted, not taken for the worst.
    (folder / "format.json").write_text(json.dumps({"views": {n: {"alignment": None if c == 0.96 else {"scale": c}}
                                                              for n, c in zip(names, scales)}}))
    mean = sparse_prior_accuracy.main(args)["scenes"][scene_dir.name]["mean"]
    assert mean["scale_error"] == pytest.approx(0.01) and mean["unaligned_views"] == 1
    assert "(1 view(s) unaligned)" in capsys.readouterr().out


def test_an_llff_folder_trimmed_to_another_resolution_needs_its_downscale(tmp_path):
    import sparse_runs

    scene = tmp_path / "room"
    (scene / "images_2").mkdir(parents=True)
    np.save(scene / "poses_bounds.npy", np.zeros((3, 17)))
    protocol = sparse_runs.PROTOCOLS["llff3"]
    with pytest.raises(SystemExit, match=r"has no images_8/ .*it holds images_2: give it as .*room@N"):
        sparse_runs.parse_scene(str(scene), protocol)
    assert sparse_runs.parse_scene(f"{scene}@2", protocol).downscale == 2


def test_a_reference_depth_made_at_another_size_names_both_sizes(tmp_path):
    np.savez(tmp_path / sparse_data.REFERENCE_FILE, __size__=np.array([480, 270]))
    with pytest.raises(SystemExit, match=r"made for 480x270 images, but the scene is served at 240x135: .*@N"):
        sparse_data.read_reference_depth(tmp_path, [], 240, 135)
    assert sparse_data.read_reference_depth(tmp_path, [], 480, 270) == {}


def test_marr_settings_reach_every_worker_and_bad_ones_are_refused():
    scene = synthetic_dir("orbit")
    base = ["--protocol", "m360_24", "--scenes", str(scene), "--settings", "preset,wo_confidence"]
    args, scenes, *_ = sparse.parse(base + ["--marr", "confidence_power=4", "--marr", "alpha_min=0.2"])
    assert args.marr_settings == {"confidence_power": 4.0, "alpha_min": 0.2}
    cmd = sparse.worker_cmd(args, "run", scenes[0], sparse_runs.Run(args.tag, scenes[0], "preset", 0))
    assert " ".join(cmd).count("--marr") == 2 and "confidence_power=4" in cmd and "alpha_min=0.2" in cmd
    with pytest.raises(SystemExit, match="--marr power=2: expected KEY=VALUE"):
        sparse.parse(base + ["--marr", "power=2"])
    with pytest.raises(SystemExit, match="not a number"):
        sparse.parse(base + ["--marr", "confidence_power=high"])
    with pytest.raises(SystemExit, match=">= 0"):
        sparse.parse(base + ["--marr", "confidence_power=-1"])


def test_scores_along_the_runs_keep_the_steps_every_seed_has():
    def run(seed, history, final, **extra):
        return {"scene": "a", "setting": "preset", "seed": seed, "steps": 3000, "psnr": final,
                "history": [{"step": st, "psnr": p} for st, p in history], **extra}
    runs = [run(0, [(1000, 20.0), (2000, 22.0)], 23.0), run(1, [(1000, 21.0)], 24.0)]  # seed 1 missed step 2000
    along = sparse_along.along_runs(runs, ["baseline", "preset"])["a"]
    assert list(along) == ["preset"] and list(along["preset"]) == [1000, 3000]
    assert along["preset"][1000] == pytest.approx((20.5, 0.5)) and along["preset"][3000] == pytest.approx((23.5, 0.5))
    early = [{**r, "scored_at_step": 1000} for r in runs]  # tabulated at an earlier step: the final is not that step's
    assert list(sparse_along.along_runs(early, ["preset"])["a"]["preset"]) == [1000]
