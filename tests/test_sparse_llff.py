"""The real few-view protocol (issue 15): the LLFF split of FSGS / DNGaussian, no all-view SfM points in a few-view
scene, training-camera extent, the sparse_llff preset pair, and the all-view reference points priors are scored
against."""
import shutil
from pathlib import Path

import numpy as np
import pytest

from data_fixtures import write_rgb
from warpgs.config.loader import load_config
from warpgs.data import Camera, PointCloud, SceneError, llff_split, load_scene, look_at, save_colmap
from warpgs.data.depth.evaluate import point_depth_metrics
from warpgs.data.depth.reference_points import (read_points3d_tracks, reference_depth, sparse_depth_map,
                                                view_reference_points)
from warpgs.data.formats.llff import POSES_FILE, save_poses_bounds

ROOT = Path(__file__).resolve().parents[1]
FERN = ROOT / "data" / "fern"
W, H, F = 64, 48, 55.0


def fsgs_split(num_views: int, n_views: int, llffhold: int = 8):
    """FSGS's / DNGaussian's LLFF reader, transcribed (dataset_readers.readColmapSceneInfo): indices, not cams."""
    cam_infos = list(range(num_views))
    train = [c for idx, c in enumerate(cam_infos) if idx % llffhold != 0]
    test = [c for idx, c in enumerate(cam_infos) if idx % llffhold == 0]
    idx_sub = [round(i) for i in np.linspace(0, len(train) - 1, n_views)]
    return [c for idx, c in enumerate(train) if idx in idx_sub], test


@pytest.mark.parametrize("num_views", [9, 17, 20, 25, 34, 41, 55, 62])
def test_llff_split_is_the_few_view_papers_split(num_views):
    for n in (1, 2, 3, 4, 5, 6, 9):
        if n > num_views - len(range(0, num_views, 8)):
            continue
        assert llff_split(num_views, n) == fsgs_split(num_views, n), (num_views, n)


def test_n_train_needs_held_out_views():
    from warpgs.data.formats.splits import resolve_split

    with pytest.raises(ValueError, match="n_train=3 needs a split that holds views out"):
        resolve_split(Path("."), [f"v{i}" for i in range(10)], "all", 3)


def _cameras(n=12, seed=0):
    rng = np.random.default_rng(seed)
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
    cams = []
    for i in range(n):
        eye = np.array([rng.uniform(-1, 1), -4.0 + rng.uniform(-0.3, 0.3), rng.uniform(-0.6, 0.6)])
        cams.append(Camera(K, look_at(eye, rng.normal(scale=0.2, size=3)), W, H, name=f"IMG_{100 + i}.JPG"))
    return cams


def _tracked_points(cams, n=200, seed=1):
    """Points in front of the cameras, each seen by a random subset of at least two views."""
    rng = np.random.default_rng(seed)
    xyz = rng.normal(scale=0.4, size=(n, 3))
    seen = rng.random((len(cams), n)) < 0.6
    seen[:2, :] = True
    return PointCloud(xyz, np.full((n, 3), 0.5), [np.nonzero(s)[0] for s in seen])


def _bounds(cams, points):
    """LLFF's near/far: the 0.1 / 99.9 percentiles of the camera z of the points each view's track holds."""
    return np.array([np.percentile(c.world_to_camera(points.xyz[o])[:, 2], [0.1, 99.9])
                     for c, o in zip(cams, points.observed_by)])


def _llff_with_model(root: Path, cams, points, *, images_bin=True):
    for i, cam in enumerate(cams):
        write_rgb(root / "images" / cam.name, W, H, seed=i)
    save_poses_bounds(cams, root / POSES_FILE, _bounds(cams, points))
    save_colmap(cams, root / "sparse" / "0", points, binary=True)
    if not images_bin:
        (root / "sparse" / "0" / "images.bin").unlink()
    return root


def test_a_few_view_scene_gets_no_all_view_points(tmp_path):
    cams = _cameras()
    points = _tracked_points(cams)
    _llff_with_model(tmp_path, cams, points)
    full = load_scene(tmp_path)
    assert full.points is not None and len(full.points) == len(points)  # the all-view protocol keeps them
    few = load_scene(tmp_path, split="llff", n_train=3)
    assert (few.train, few.test) == fsgs_split(12, 3)
    assert few.points is None and "withheld" in few.metadata["colmap_points"]


def test_camera_extent_is_that_of_the_training_cameras(tmp_path):
    cams = _cameras()
    _llff_with_model(tmp_path, cams, _tracked_points(cams))
    few = load_scene(tmp_path, split="llff", n_train=3)
    centres = np.stack([cams[i].center for i in few.train])
    want = 1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max()
    assert few.camera_extent() == pytest.approx(want)
    every = np.stack([c.center for c in cams])
    assert want < 1.1 * np.linalg.norm(every - every.mean(0), axis=1).max()  # the test cameras would change it


def test_reference_points_follow_their_tracks(tmp_path):
    cams = _cameras()
    points = _tracked_points(cams)
    _llff_with_model(tmp_path, cams, points)
    scene = load_scene(tmp_path, split="all")
    ref, per_view = view_reference_points(scene)
    np.testing.assert_allclose(ref.xyz, points.xyz, atol=1e-6)  # float32 -> double round trip
    assert [list(p) for p in per_view] == [list(o) for o in points.observed_by]


def test_without_images_bin_the_ids_are_checked_against_the_llff_bounds(tmp_path):
    cams = _cameras()
    points = _tracked_points(cams)
    _llff_with_model(tmp_path, cams, points, images_bin=False)  # as fern ships sparse/0
    scene = load_scene(tmp_path, split="all")
    _, per_view = view_reference_points(scene)
    assert [list(p) for p in per_view] == [list(o) for o in points.observed_by]
    # Bounds that do not come from these tracks (here: views 3 and 4 swapped) leave the ids unknown.
    bounds = _bounds(cams, points)
    bounds[[3, 4]] = bounds[[4, 3]]
    save_poses_bounds(cams, tmp_path / POSES_FILE, bounds)
    with pytest.raises(SceneError, match="cannot tell which view track id 4"):
        view_reference_points(load_scene(tmp_path, split="all"))


def test_a_broken_points3d_file_is_named(tmp_path):
    cams = _cameras(n=3)
    save_colmap(cams, tmp_path, _tracked_points(cams, n=20), binary=True)
    path = tmp_path / "points3D.bin"
    assert len(read_points3d_tracks(path).xyz) == 20
    data = path.read_bytes()
    path.write_bytes(data[:-5])
    with pytest.raises(SceneError, match=r"points3D\.bin.*truncated"):
        read_points3d_tracks(path)
    path.write_bytes((10 ** 12).to_bytes(8, "little") + data[8:])
    with pytest.raises(SceneError, match=r"points3D\.bin.*declares"):
        read_points3d_tracks(path)


def test_sparse_depth_keeps_the_nearest_point_per_pixel():
    cam = Camera(np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]]), np.eye(4), W, H)
    xyz = np.array([[0.0, 0.0, 4.0], [0.0, 0.0, 2.0], [0.5, 0.0, 3.0], [0.0, 0.0, -1.0]])  # last: behind
    depth = sparse_depth_map(cam, xyz)
    assert depth[H // 2, W // 2] == pytest.approx(2.0)
    assert (depth > 0).sum() == 2


def test_point_metrics_reward_a_confidence_that_ranks_errors():
    cam = Camera(np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]]), np.eye(4), W, H)
    rng = np.random.default_rng(0)
    z_true = rng.uniform(2, 6, (H, W))
    wrong = rng.random((H, W)) < 0.3
    inv = np.where(wrong, 1 / (1.5 * z_true), 1 / z_true)  # 30 % of pixels 50 % too far
    rows, cols = np.mgrid[0:H, 0:W]
    pix = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], 1)
    xyz = np.stack([(pix[:, 0] - W / 2) / F, (pix[:, 1] - H / 2) / F, np.ones(H * W)], 1) * z_true.reshape(-1, 1)
    pix, z = reference_depth(cam, xyz)
    good = point_depth_metrics(inv, np.ones((H, W), bool), pix, z, np.where(wrong, 0.1, 0.9))
    blind = point_depth_metrics(inv, np.ones((H, W), bool), pix, z, np.full((H, W), 0.5))
    assert good["top"]["0.5"]["abs_rel"] == pytest.approx(0.0, abs=1e-9)  # the confident half is all right
    assert blind["top"]["0.5"]["abs_rel"] > 0.05
    assert good["abs_rel_weighted"] < blind["abs_rel_weighted"] == pytest.approx(blind["abs_rel"])
    assert good["point_coverage"] == 1.0 and good["delta_1_25"] == pytest.approx(1 - wrong.mean(), abs=1e-9)


def test_the_preset_pair_differs_only_in_the_method():
    method, base = load_config(ROOT / "configs" / "sparse_llff.yaml"), load_config(
        ROOT / "configs" / "sparse_llff_baseline.yaml")
    for cfg in (method, base):
        d = cfg.data
        assert (d.split, d.n_train, d.downscale, cfg.model.init) == ("llff", 3, 8, "triangulate")
    assert base.data.depth_priors in (None, "none") and method.data.depth_priors == "estimate"
    assert set(base.losses) == {"l1", "dssim"}
    assert set(method.losses) == {"l1", "dssim", "depth", "depth_grad", "depth_local", "opacity", "scale", "count"}
    # The method also starts from points lifted from its prior; the baseline, which has none, from the
    # triangulated points alone. The method adds primitive dropout at few views and unpooling beyond a few (virtual
    # views are off in both).
    assert method.model.prior_points > 0 and base.model.prior_points == 0
    assert method.train.virtual_views == 0 and base.train.virtual_views == 0
    assert method.train.drop_rate == "auto" and base.train.drop_rate == 0
    assert method.strategy.unpool_every == "auto" and base.strategy.unpool_every == 0
    assert base.strategy.prune_world_scale == 0  # in both (a == b below): it deletes a sparse capture's background
    a, b = method.to_dict(), base.to_dict()
    for cfg in (a, b):
        cfg.pop("losses")
        cfg["data"].pop("depth_priors")
        cfg["model"].pop("prior_points")
        cfg["model"].pop("prior_points_confidence")
        cfg["train"].pop("virtual_views")
        cfg["train"].pop("drop_rate")
        cfg["strategy"].pop("unpool_every")
    assert a == b


def test_the_drivers_name_an_override_that_a_setting_replaces(capsys):
    import sys

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import ablation

    ablation.warn_replaced_overrides({"baseline_prior_points": ["model.prior_points=20000"], "wo_depth": []},
                                     ["model.prior_points=5000", "u=1"])
    err = capsys.readouterr().err
    assert "setting baseline_prior_points sets model.prior_points itself" in err and "model.prior_points=5000" in err
    assert "wo_depth" not in err and "u=1" not in err


def test_the_drivers_refuse_an_override_that_changes_no_run():
    import sys

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import ablation

    with pytest.raises(SystemExit, match="model.prior_points=5000 would change no run.*baseline_prior_points"):
        ablation.warn_replaced_overrides({"baseline_prior_points": ["model.prior_points=20000"]},
                                         ["model.prior_points=5000", "u=1"])


def test_the_real_ablation_removes_each_term_once():
    import sys

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import ablation

    keys = [s[0] for s in ablation.REAL_SETTINGS]
    assert keys[0] == "baseline" and keys[-1] == "full" and len(set(keys)) == len(keys)
    # the preset plus one thing beyond the paper
    added = {"unpool": ["strategy.unpool_every=1"], "virtual": ["train.virtual_views=auto"],
             "wo_drop": ["train.drop_rate=0"], "wo_unpool": ["strategy.unpool_every=0"],
             "depth_patch": ["losses.depth_patch.weight=0.1", "losses.depth_patch.schedule=[exp, 1.0, 0.01, 0, 10000]"]}
    removed = [o for key, _, preset, overrides, _ in ablation.REAL_SETTINGS if preset == "sparse_llff"
               and key not in added for o in overrides if o not in ablation.PAPER_TERMS]
    assert removed == [f"losses.{t}=0" for t in ("depth", "depth_grad", "depth_local", "opacity", "scale", "count")] \
        + ["model.prior_points=0"]
    # The preset leaves the paper's opacity and scale terms out and adds primitive dropout at few views: "full" (the
    # paper's objective) and every "w/o" row put the terms back and take the additions out; "preset" is the preset.
    settings = {k: o for k, _, preset, o, _ in ablation.REAL_SETTINGS if preset == "sparse_llff"}
    sparse_llff = load_config(ROOT / "configs" / "sparse_llff.yaml")
    assert sparse_llff.losses["scale"] == 0 and sparse_llff.losses["opacity"] == 0
    assert sparse_llff.train.virtual_views == 0 and sparse_llff.train.drop_rate == "auto"
    assert sparse_llff.strategy.unpool_every == "auto"
    assert settings["full"] == ablation.PAPER_TERMS == ["losses.opacity=0.05", "losses.scale=0.008",
                                                        "train.virtual_views=0", "train.drop_rate=0",
                                                        "strategy.unpool_every=0"]
    n = len(ablation.PAPER_TERMS)
    assert all(o[:n] == ablation.PAPER_TERMS for k, o in settings.items() if k != "preset" and k not in added)
    assert settings["preset"] == [] and settings["wo_scale"] == ablation.PAPER_TERMS + ["losses.scale=0"]
    assert all(settings[k] == o for k, o in added.items())
    # The initialisation's share: 3DGS with the method's initial points and prior, none of its losses.
    plus = [s for s in ablation.REAL_SETTINGS if s[0] == "baseline_prior_points"]
    assert plus and plus[0][2] == "sparse_llff_baseline" and ablation.uses_prior(*plus[0][2:4])
    method_model = load_config(ROOT / "configs" / "sparse_llff.yaml").model
    assert plus[0][3] == [f"model.prior_points={method_model.prior_points}",
                          f"model.prior_points_confidence={method_model.prior_points_confidence}"]
    assert not ablation.uses_prior("sparse_llff_baseline", [])
    # A CPU budget scales the prior points with it (20k of 200k -> 1k of 10k), before the user's overrides.
    assert ablation.prior_points_for_budget("sparse_llff", [], 10_000) == ["model.prior_points=1000"]
    assert ablation.prior_points_for_budget("sparse_llff", [], None) == []
    assert ablation.prior_points_for_budget("sparse_llff", ["model.prior_points=0"], 10_000) == []
    assert ablation.prior_points_for_budget("sparse_llff_baseline", [], 10_000) == []
    run = ablation.setting_overrides_for_run
    assert run("sparse_llff", ["losses.depth=0"], 10_000, ["u=1"]) == ["model.prior_points=1000", "u=1",
                                                                        "losses.depth=0"]
    assert run("sparse_llff", ["model.prior_points=0"], 10_000, ["u=1"]) == ["u=1", "model.prior_points=0"]
    assert run("sparse_llff_baseline", ["model.prior_points=20000"], None, []) == ["model.prior_points=20000"]
    assert run("sparse_llff_baseline", ["model.prior_points=20000"], 10_000, []) == ["model.prior_points=1000"]
    # ... and a user's override of a key the setting sets is named, not silently dropped.
    replaced = ablation.user_overrides_replaced(plus[0][3], ["model.prior_points=5000", "u=1"])
    assert replaced == ["model.prior_points=5000"]
    assert ablation.user_overrides_replaced(["losses.depth=0"], ["model.prior_points=5000"]) == []
    # The scaled schedule of a short real run keeps the preset's shape: densify until half the run.
    assert "strategy.refine_stop=150" in ablation.schedule_overrides(300, 10_000)
    assert ablation.schedule_overrides(10_000, 10_000) == []


@pytest.mark.skipif(not (FERN / POSES_FILE).is_file() or not (FERN / "sparse/0/points3D.bin").is_file(),
                    reason="LLFF fern with its SfM points not present (data/ is git-ignored)")
def test_fern_protocol_and_reference():
    scene = load_scene(FERN, downscale=8, split="llff", n_train=3)
    assert (scene.train, scene.test) == ([1, 10, 19], [0, 8, 16])
    assert scene.points is None and (scene.cameras[0].width, scene.cameras[0].height) == (504, 378)
    ref, per_view = view_reference_points(scene)  # fern has no images.bin: ids checked against the bounds
    assert len(ref.xyz) == 10091 and all(len(p) > 1000 for p in per_view)
