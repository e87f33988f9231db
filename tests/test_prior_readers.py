"""What reads depth priors, and what the trainer does about a scene without them: loss terms declare the batch
fields they need (register_loss(batch=...)); with data.depth_priors=auto a scene without priors gets estimated
ones when something reads them, and 'none' with a reader is refused at set-up, not at the first step."""
import math

import pytest
from test_sparse_train import CONFIGS, run, tiny_lightfield

from warpgs.losses import register_loss, required_batch_fields, resolve_losses, unregister_loss
from warpgs.losses.marr import PRIOR_KEY
from warpgs.train.trainer import Trainer


def test_the_depth_terms_declare_the_prior_and_only_active_terms_count():
    terms = resolve_losses({"l1": 1.0, "depth": 1.0, "depth_grad": 0.0, "depth_local": 0.5, "opacity": 0.05})
    assert required_batch_fields(terms) == {PRIOR_KEY: ["depth", "depth_local"]}
    assert required_batch_fields(resolve_losses({"l1": 1.0, "dssim": 0.2})) == {}
    assert resolve_losses({"depth_patch": 0.1})[0].batch == (PRIOR_KEY,)


def test_a_registered_loss_declares_its_own_batch_fields():
    @register_loss("test_reads_masks", outputs=("alpha",), batch=("mask",))
    def reads_masks(render_out, batch, model, step):
        return render_out["alpha"].mean()

    try:
        assert required_batch_fields(resolve_losses({"test_reads_masks": 1.0})) == {"mask": ["test_reads_masks"]}
    finally:
        unregister_loss("test_reads_masks")


def test_auto_estimates_priors_for_a_scene_without_them(tmp_path, capsys):
    """The tiny light field keeps its priors in priors/, which 'auto' does not look in: to 'auto' it has none."""
    trainer = run(tmp_path, "data.depth_priors=auto")
    assert "depth priors: the scene at" in capsys.readouterr().err
    assert len(sorted((tmp_path / "depth_priors").glob("*.exr"))) == len(trainer.scene.train)
    batch = trainer.make_batch(trainer.view(trainer.train_indices[0]), 0)
    assert bool(batch["inv_depth_valid"].any())
    info = trainer.train_step()
    assert {"depth", "depth_grad", "depth_local"} <= set(info["values"])
    assert all(math.isfinite(v) for v in info["values"].values())


def test_a_run_that_reads_priors_says_how_much_of_the_views_they_cover(tmp_path, capsys):
    import numpy as np

    from warpgs.data.depth.coverage import prior_coverage

    trainer = run(tmp_path, "data.depth_priors=estimate")
    err = capsys.readouterr().err
    scene = trainer.scene
    shares = [float(scene.inv_depth_prior_np(v)[1].mean()) for v in scene.train]
    stats = prior_coverage(scene, scene.train)
    assert stats["views"] == len(scene.train) and math.isclose(stats["valid"], np.mean(shares), rel_tol=1e-6)
    assert stats["valid_min"] == min(shares) and stats["valid_max"] == max(shares) and 0 < stats["valid"] <= 1
    assert stats["confident"] is not None and stats["confident"] <= stats["valid"]  # the sweep writes a confidence
    line = next(ln for ln in err.splitlines() if ln.startswith("depth priors: valid on"))
    assert f"{100 * stats['valid']:.0f}% of the pixels of the {len(scene.train)} training views" in line
    assert prior_coverage(scene, []) is None
    # A run that reads no prior says nothing about one.
    run(tmp_path / "none", "data.depth_priors=auto", "losses.depth=0", "losses.depth_grad=0", "losses.depth_local=0")
    assert "depth priors: valid on" not in capsys.readouterr().err


def test_auto_leaves_a_scene_alone_when_nothing_reads_priors(tmp_path):
    trainer = run(tmp_path, "data.depth_priors=auto", "losses.depth=0", "losses.depth_grad=0", "losses.depth_local=0")
    assert not (tmp_path / "depth_priors").exists()
    assert not trainer.scene.has("depth_prior", trainer.scene.train)


def test_none_with_a_reader_is_refused_at_set_up(tmp_path):
    with pytest.raises(ValueError, match=r"data.depth_priors: 'none', but losses.depth, losses.depth_grad, "
                                         r"losses.depth_local read depth priors"):
        run(tmp_path, "data.depth_priors=none")
    with pytest.raises(ValueError, match=r"data.depth_priors: 'none', but model.prior_points read"):
        Trainer(CONFIGS / "sparse_baseline.yaml", quiet=True, overrides=[
            f"data.path={tiny_lightfield()}", "data.depth_priors=none", "model.prior_points=100",
            "train.device=cpu", "train.steps=2", "train.progress=false", f"output.dir={tmp_path}"])


def test_virtual_views_on_auto_read_priors_only_when_they_turn_on():
    from warpgs.config import load_config
    from warpgs.train.setup import what_reads_priors

    cfg = load_config(CONFIGS / "sparse_llff.yaml")
    terms = resolve_losses({"l1": 1.0})
    cfg.model.prior_points = 0
    cfg.train.virtual_views = "auto"
    assert what_reads_priors(cfg, terms, 3) == "train.virtual_views"
    assert what_reads_priors(cfg, terms, 24) == ""
