"""The sparse-view preset through the real trainer on a tiny light field: the batch carries the prior under the
names the depth terms read, every term is computed, and ablating the depth terms stops rendering depth."""
import atexit
import functools
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from train_fixtures import Interrupt

from warpgs.data.depth.files import write_exr
from warpgs.data.formats.load import load_scene
from warpgs.data.formats.synthetic import RigSettings, write_synthetic_scene
from warpgs.train.trainer import Trainer

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
_ROOT = Path(tempfile.mkdtemp(prefix="warpgs-sparse-tests-"))
atexit.register(shutil.rmtree, _ROOT, ignore_errors=True)


@functools.lru_cache(maxsize=None)
def tiny_lightfield() -> Path:
    """3x3 array + 4 off-array views at 40x30, with exact inverse depth as its priors (depth_priors/)."""
    root = write_synthetic_scene(_ROOT / "lf40", "lightfield", RigSettings(width=40, height=30), n_points=600)
    scene = load_scene(root)
    for v in scene.train:
        d, valid = scene.depth_np(v)
        ok = valid & np.isfinite(d) & (d > 0)
        write_exr(root / "priors" / f"{Path(scene.names[v]).stem}.exr",
                  np.where(ok, 1.0 / np.where(ok, d, 1.0), 0.0).astype(np.float32), "inverse_depth", ok)
    return root


def run(tmp_path, *extra, steps=6, callbacks=()):
    overrides = [f"data.path={tiny_lightfield()}", "data.depth_priors=priors", f"train.steps={steps}",
                 "train.device=cpu", "train.progress=false", "train.checkpoint_every=0", "eval.every=0",
                 "eval.lpips=false", "eval.save_images=false", "model.sh_degree=0", "strategy.refine_start=2",
                 "strategy.refine_every=2", "strategy.max_primitives=2000", f"output.dir={tmp_path}", *extra]
    return Trainer(CONFIGS / "sparse_lightfield.yaml", overrides=overrides, quiet=True, callbacks=callbacks)


def test_method_trains_with_every_term(tmp_path):
    trainer = run(tmp_path)
    assert trainer.outputs == ("rgb", "alpha", "inv_depth")
    batch = trainer.make_batch(trainer.view(trainer.train_indices[0]), 0)
    assert batch["inv_depth_prior"].shape == (30, 40, 1)
    assert batch["inv_depth_valid"].dtype == torch.bool and bool(batch["inv_depth_valid"].any())
    info = trainer.train_step()
    assert set(info["values"]) == {"l1", "dssim", "depth", "depth_grad", "depth_local", "opacity", "scale", "count"}
    assert all(math.isfinite(v) for v in info["values"].values())
    for _ in range(5):
        info = trainer.train_step()
    assert math.isfinite(info["loss"])


def test_depth_ablation_renders_no_depth(tmp_path):
    trainer = run(tmp_path, "losses.depth=0", "losses.depth_grad=0", "losses.depth_local=0")
    assert trainer.outputs == ("rgb",)
    info = trainer.train_step()
    assert set(info["values"]) == {"l1", "dssim", "opacity", "scale", "count"}


def test_estimated_priors_are_written_to_the_output_folder(tmp_path):
    """data.depth_priors=estimate: plane-sweep stereo aligned to the SfM points, written under the run's output
    folder (the scene folder is left as it was), and the depth terms train on it."""
    scene_files_before = sorted(p.relative_to(tiny_lightfield()) for p in tiny_lightfield().rglob("*"))
    trainer = run(tmp_path, "data.depth_priors=estimate")
    written = sorted((tmp_path / "depth_priors").glob("*.exr"))
    assert len(written) == len(trainer.scene.train)
    assert sorted(p.relative_to(tiny_lightfield()) for p in tiny_lightfield().rglob("*")) == scene_files_before
    batch = trainer.make_batch(trainer.view(trainer.train_indices[0]), 0)
    valid = batch["inv_depth_valid"]
    assert bool(valid.any())
    # Aligned to the scene's metric depth: compare with the exact inverse depth where both are defined.
    d, ok = trainer.scene.depth_np(trainer.train_indices[0])
    exact = torch.from_numpy(np.where(ok, 1.0 / np.where(ok, d, 1.0), 0.0)).float()[..., None].to(valid.device)
    both = valid & torch.from_numpy(ok)[..., None].to(valid.device)
    rel = ((batch["inv_depth_prior"] - exact).abs() / exact.clamp_min(1e-6))[both]
    assert rel.median() < 0.1, rel.median()
    info = trainer.train_step()
    assert {"depth", "depth_grad", "depth_local"} <= set(info["values"])
    assert all(math.isfinite(v) for v in info["values"].values())


def test_estimated_priors_are_reused_by_a_later_trainer(tmp_path, monkeypatch):
    run(tmp_path, "data.depth_priors=estimate")
    stamps = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "depth_priors").glob("*.exr")}
    import warpgs.data as data

    def no_estimate(*args, **kwargs):
        raise AssertionError("the priors were estimated again")

    monkeypatch.setattr(data, "compute_depth_priors", no_estimate)
    again = run(tmp_path, "data.depth_priors=estimate")
    assert all(again.scene.files[v].depth_prior is not None for v in again.scene.train)
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "depth_priors").glob("*.exr")} == stamps


def test_a_run_with_another_output_folder_copies_the_cached_priors(tmp_path, monkeypatch, capsys):
    """Estimated priors are also kept in $WARPGS_CACHE/depth_priors/<key>: a new output folder on the same scene,
    views and settings copies them instead of estimating again; other settings are another entry."""
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    first = run(tmp_path / "a", "data.depth_priors=estimate")
    import warpgs.data as data

    def no_estimate(*args, **kwargs):
        raise AssertionError("the priors were estimated again")

    with monkeypatch.context() as m:
        m.setattr(data, "compute_depth_priors", no_estimate)
        second = run(tmp_path / "b", "data.depth_priors=estimate")
    assert "copied from" in capsys.readouterr().err
    for v in first.scene.train:
        a, b = first.scene.files[v].depth_prior, second.scene.files[v].depth_prior
        assert b.parent == tmp_path / "b" / "depth_priors" and a.read_bytes() == b.read_bytes()
    run(tmp_path / "c", "data.depth_priors=estimate", "data.depth_prior_fill=0.3")
    assert len(list((tmp_path / "cache" / "depth_priors").iterdir())) == 2


def test_priors_are_estimated_again_when_the_fill_changes(tmp_path):
    run(tmp_path, "data.depth_priors=estimate")
    plain = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "depth_priors").glob("*.exr")}
    again = run(tmp_path, "data.depth_priors=estimate", "data.depth_prior_fill=0.3")
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "depth_priors").glob("*.exr")} != plain
    v = again.train_indices[0]
    conf = again.scene.prior_confidence_np(v)
    assert conf is not None and np.isclose(conf, 0.3).any()  # filled pixels carry the fill's confidence


def test_prior_options_reach_the_estimator_and_a_change_re_estimates(tmp_path):
    import json

    import pytest

    run(tmp_path, "data.depth_priors=estimate")
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "depth_priors").glob("*.exr")}
    run(tmp_path, "data.depth_priors=estimate", "data.depth_prior_options={window: 7}")
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "depth_priors").glob("*.exr")} != before
    made = json.loads((tmp_path / "depth_priors" / "format.json").read_text())
    assert made["estimator_settings"]["window"] == 7
    with pytest.raises(ValueError, match="data.depth_prior_options"):
        run(tmp_path / "bad", "data.depth_priors=estimate", "data.depth_prior_options={windows: 7}")


def test_prior_points_join_the_initial_model_after_the_prior_is_estimated(tmp_path):
    """model.prior_points (configs/sparse_llff.yaml's start): the prior is estimated first, then its confident
    pixels become initial primitives on top of the scene's points, and the run trains."""
    plain = run(tmp_path / "plain", "data.depth_priors=estimate")
    trainer = run(tmp_path / "lifted", "data.depth_priors=estimate", "model.prior_points=300")
    assert trainer.model.num_primitives == plain.model.num_primitives + 300
    assert "300 from depth priors" in trainer.init_source
    info = trainer.train_step()
    assert math.isfinite(info["loss"])


def test_a_run_cut_from_a_longer_schedule_is_that_schedules_first_steps(tmp_path):
    """configs/sparse_llff_baseline.yaml trains the first 1000 steps of a 10k schedule: with the position lr's and
    the depth weights' horizons set to the longer run's length, an 8-step run ends where the 20-step run is after
    its 8th step, bit for bit (densification included: both stop it at their own end or at refine_stop)."""
    horizon = ["optim.means_lr_steps=20"] + [f"losses.{t}.schedule=[exp,1.0,0.01,0,20]"
                                            for t in ("depth", "depth_grad", "depth_local")]
    cut = run(tmp_path / "cut", *horizon, steps=8)
    cut.fit()
    # The longer run is scored on its test views every 4 steps (the benchmark's history): scoring changes nothing.
    longer = run(tmp_path / "long", *horizon, "eval.every=4", steps=20, callbacks=[Interrupt(8)])
    with pytest.raises(KeyboardInterrupt):
        longer.fit()
    assert longer.step == cut.step == 8
    assert cut.model.num_primitives == longer.model.num_primitives
    for name, value in cut.model.params.items():
        assert torch.equal(value, longer.model.params[name]), name
    # Without the horizons the 8-step run decays both over its own length and ends elsewhere.
    own = run(tmp_path / "own", steps=8)
    own.fit()
    assert not torch.equal(own.model.params["means"], cut.model.params["means"])


def test_a_thin_triangulation_starts_beside_the_prior_points_and_stops_without_them(tmp_path, monkeypatch):
    """model.init=triangulate finding under MIN_TRIANGULATED_POINTS_STRICT points (12 views around a capture's
    textureless backdrop gave 19): with the prior's lifted points beside them the run starts from both, saying so;
    asked for alone, it is the error naming model.init=auto."""
    from warpgs.data import PointCloud
    from warpgs.data.errors import SceneError
    from warpgs.data.sfm.triangulate import Triangulation

    few = PointCloud(np.zeros((5, 3), np.float32), np.full((5, 3), 0.5, np.float32))
    monkeypatch.setattr("warpgs.data.sfm.triangulate.triangulate_scene",
                        lambda scene, cache_dir, **kw: Triangulation(few, 0.4, 0.1, False, {}))
    trainer = run(tmp_path / "lifted", "data.depth_priors=estimate", "model.init=triangulate", "model.prior_points=300")
    assert trainer.model.num_primitives == 5 + 300
    assert "5 points, 0.40 px; under 20" in trainer.init_source and "300 from depth priors" in trainer.init_source
    assert math.isfinite(trainer.train_step()["loss"])
    with pytest.raises(SceneError, match="only 5 points.*model.init=auto"):
        run(tmp_path / "alone", "data.depth_priors=estimate", "model.init=triangulate", "model.prior_points=0")
