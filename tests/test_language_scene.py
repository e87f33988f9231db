"""End to end on the built-in synthetic scene: train the language field with the trainer (configs/language.yaml,
shortened), then text queries (mIoU / mAP), 3D delete / extract, click-to-segment and the warpgs-query CLI.

One short run is shared by the tests of this module (48x36 orbit, 14 training views, 800 surfels, 160 steps).
"""
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import warpgs.language  # noqa: F401  (registers the extension and losses)
from warpgs.data import make_synthetic_scene
from warpgs.language.cli import query_main
from warpgs.language.query import LanguageField
from warpgs.train.trainer import Trainer

CONFIG = Path(__file__).resolve().parent.parent / "configs" / "language.yaml"
STEPS = 160
# Stated accuracies after the short run (measured on this setup: see docs/language.md for the numbers).
MIN_MIOU = 0.4
MIN_MAP = 0.6
MIN_RED_SPHERE_IOU = 0.4


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("language")
    make_synthetic_scene(root / "scene", "orbit", width=48, height=36, n_points=800, n_orbit=16)
    overrides = [f"steps={STEPS}", "device=cpu", f"data.path={root / 'scene'}", "model.sh_degree=0",
                 "eval.every=0", "eval.lpips=false", "eval.save_images=false", "train.checkpoint_every=0",
                 "train.progress=false", "strategy.refine_start=100000", "extensions.language.ae_steps=300",
                 "extensions.language.latent_lr=0.01", "extensions.language.bridge_start=80",
                 "extensions.language.alternate_period=40"]
    seen = {}

    def last_language_terms(trainer, step, info):  # the extension's deferred key, read as a user callback would
        seen.update(step=step, terms=info["language"])

    trainer = Trainer(str(CONFIG), overrides=overrides, out_dir=root / "run", quiet=True,
                      callbacks=[last_language_terms])
    trainer.fit()
    trainer.seen_terms = seen
    return trainer


def test_training_writes_language_outputs(run):
    out = Path(run.out_dir)
    for name in ("checkpoint.pt", "point_cloud.ply", "metrics.json", "language_metrics.json",
                 "language/autoencoder.pt", "language/meta.json"):
        assert (out / name).is_file(), name
    assert run.model.params["lang"].shape == (run.model.num_primitives, 8)
    eps = torch.sigmoid(run.model.params["lang_eps"])
    assert bool(((eps > 0) & (eps < 1)).all())
    sigma = run.modules["ppgs_sigma"].sigma2
    assert bool(torch.isfinite(sigma).all()) and not torch.allclose(sigma, torch.ones(2))  # the weights learnt
    assert run.seen_terms["step"] == STEPS - 1
    terms = run.seen_terms["terms"]
    assert {"l1", "l_r", "l_rec", "l_rf", "sigma2_rec", "sigma2_rf"} <= set(terms)
    assert all(type(v) is float and math.isfinite(v) for v in terms.values())
    saved = json.loads((out / "language_metrics.json").read_text())["terms"]
    assert saved == pytest.approx(terms)  # the metrics file's terms: the last step's, as floats


def test_text_queries_reach_the_stated_accuracy(run):
    m = json.loads((Path(run.out_dir) / "language_metrics.json").read_text())
    assert m["num_queries"] >= 8
    assert m["miou"] >= MIN_MIOU, m["per_label"]
    assert m["map"] >= MIN_MAP, m["per_label"]
    assert m["per_label"]["red sphere"]["iou"] >= MIN_RED_SPHERE_IOU, m["per_label"]


def _erode(mask, r=1):
    out = mask.clone()
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            out &= torch.roll(mask, (dy, dx), (0, 1))
    return out


def test_delete_and_extract_the_red_sphere(run):
    field = LanguageField.from_trainer(run)
    red = next(k for k, v in field.label_names.items() if v == "red sphere")
    views = [v for v in (run.scene.view(i) for i in run.scene.train) if int((v.labels == red).sum()) >= 30][:3]
    assert views
    selection = field.select("red sphere")
    n = int(selection.sum())
    assert 0 < n < 0.5 * run.model.num_primitives
    for view in views:
        full = field.render_rgb(view)
        gone = field.delete(view, selection)
        alone = field.extract(view, selection)
        obj = view.labels == red
        near = ~_erode(~obj, 2)  # the object and a 2-pixel band around it (blending at its rim)
        others = (view.labels > 0) & ~near
        # delete: the object's pixels change, the other labels' pixels do not
        assert float((gone - full).abs()[obj].mean()) > 0.1
        diff = (gone - full).abs().amax(-1)[others]
        assert float(diff.mean()) < 0.02 and float((diff < 0.1).float().mean()) > 0.95
        # extract: black away from the object, the object as rendered
        assert float(alone.amax(-1)[others].mean()) < 0.05
        core = _erode(obj, 1)
        assert float((alone - full).abs()[core].mean()) < 0.1


def test_click_segments_the_clicked_object(run):
    field = LanguageField.from_trainer(run)
    red = next(k for k, v in field.label_names.items() if v == "red sphere")
    view = max((run.scene.view(i) for i in run.scene.train), key=lambda v: int((v.labels == red).sum()))
    rows, cols = torch.nonzero(_erode(view.labels == red, 2), as_tuple=True)
    y, x = int(rows.float().mean()), int(cols.float().mean())
    result = field.click(view, x + 0.5, y + 0.5)
    gt = view.labels == red
    iou = float((result.mask & gt).sum()) / float((result.mask | gt).sum())
    assert iou > 0.4, iou
    sel = field.select_like(field.clicked_feature(view, x, y))
    assert 0 < int(sel.sum()) < run.model.num_primitives


def test_query_cli_writes_maps_and_masks(run, capsys):
    out = Path(run.out_dir)
    name = run.scene.cameras[run.scene.test[0]].name
    assert query_main(["--model", str(out), "--text", "red sphere", "--view", name, "--delete", "--extract",
                       "--device", "cpu"]) == 0
    stem = Path(name).stem
    folder = out / "queries" / "red_sphere"
    for suffix in ("relevancy", "overlay", "mask", "mask_overlay", "delete", "extract"):
        assert (folder / f"{stem}_{suffix}.png").is_file(), suffix
    assert json.loads((folder / "query.json").read_text())["views"][name]["mask_pixels"] > 0
    emb = out / "q.npy"
    np.save(emb, warpgs.language.hash_embedding("red sphere"))
    assert query_main(["--model", str(out), "--embedding", str(emb), "--view", name, "--device", "cpu"]) == 0
    assert (out / "queries" / "q" / f"{stem}_mask.png").is_file()
    assert query_main(["--model", str(out), "--eval", "--device", "cpu"]) == 0
    assert "mIoU" in capsys.readouterr().out
    assert query_main(["--model", str(out), "--view", "nope.png", "--text", "x"]) == 2
