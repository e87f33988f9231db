"""Points from known poses: pycolmap triangulation with fixed cameras lands on the true surfaces, is cached, and
is what model.init=auto picks for scenes with poses but no points."""
import os
import shutil
import time

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from data_fixtures import synthetic_dir, write_rgb
from warpgs.config.loader import load_config
from warpgs.data import Camera, load_scene, look_at, save_transforms
from warpgs.data.formats.llff import save_poses_bounds
from warpgs.data.sfm.triangulate import POINTS_FILE, cache_key, triangulate_from_poses, triangulate_scene
from warpgs.train.setup import initial_points


def _depth_errors(scene, points, views):
    """Relative difference between each point's depth and the exact depth map under it, over its observers."""
    errs = []
    for v in views:
        cam, obs = scene.cameras[v], points.observed_by[v]
        pix, z = cam.project(points.xyz[obs])
        col, row = np.floor(pix[:, 0]).astype(int), np.floor(pix[:, 1]).astype(int)
        depth, valid = scene.depth_np(v)
        hit = valid[row, col] & np.isfinite(depth[row, col])
        errs.append(np.abs(depth[row, col][hit] - z[hit]) / z[hit])
    return np.concatenate(errs)


@pytest.fixture(scope="module")
def orbit_points(tmp_path_factory):
    scene = load_scene(synthetic_dir("orbit"))  # 36 views, LLFF split: 31 train, 5 test
    out = tmp_path_factory.mktemp("tri")
    start = time.perf_counter()
    tri = triangulate_scene(scene, out, num_threads=1)
    return scene, out, tri, time.perf_counter() - start


def test_points_land_on_the_true_surfaces(orbit_points):
    scene, out, tri, seconds = orbit_points
    errs = _depth_errors(scene, tri.points, scene.train)
    print(f"triangulated {len(tri.points)} points from {len(scene.train)} known poses in {seconds:.1f} s, "
          f"mean reprojection error {tri.mean_error:.2f} px, depth error median {np.median(errs):.2%}, "
          f"90th percentile {np.percentile(errs, 90):.2%}")
    assert len(tri.points) > 300 and not tri.cached
    assert tri.mean_error < 1.0
    assert np.median(errs) < 0.01 and np.percentile(errs, 90) < 0.05
    # Held-out views take no part: they observe nothing.
    assert all(len(tri.points.observed_by[v]) == 0 for v in scene.test)
    assert sum(len(tri.points.observed_by[v]) > 0 for v in scene.train) >= len(scene.train) - 1
    # The poses stayed what we gave.
    model = pycolmap.Reconstruction(str(out / "model"))
    for im in model.images.values():
        np.testing.assert_allclose(im.cam_from_world().matrix(), scene.cameras[scene.index(im.name)].viewmat[:3],
                                   atol=1e-9)


def test_second_run_reuses_the_cache_and_changes_invalidate_it(orbit_points, tmp_path):
    scene, out, tri, _ = orbit_points
    again = triangulate_scene(scene, out)
    assert again.cached and len(again.points) == len(tri.points)
    np.testing.assert_array_equal(again.points.xyz, tri.points.xyz)
    cams = [scene.native_cameras[v] for v in scene.train]
    paths = [scene.files[v].image for v in scene.train]
    key = cache_key(cams, paths, {"a": 1})
    moved = [Camera(c.K, c.viewmat, c.width, c.height, name=c.name) for c in cams]
    moved[3].viewmat[0, 3] += 1e-3
    assert cache_key(moved, paths, {"a": 1}) != key
    assert cache_key(cams, paths, {"a": 2}) != key
    # An edited image file (here: a new modification time) triangulates again; untouched files reuse the cache.
    views = scene.train[:6]
    local = [shutil.copy(scene.files[v].image, tmp_path / scene.names[v]) for v in views]
    assert not _triangulate_files(tmp_path, scene, views, local).cached
    assert _triangulate_files(tmp_path, scene, views, local).cached
    os.utime(local[2], ns=(time.time_ns(), time.time_ns() + 10**9))
    assert not _triangulate_files(tmp_path, scene, views, local).cached


def _triangulate_files(tmp_path, scene, views, paths):
    return triangulate_from_poses([scene.native_cameras[v] for v in views], paths, tmp_path / "cache",
                                  view_ids=views, n_views=len(scene), num_threads=1, progress=False)


def _config(out_dir, init="auto"):
    return load_config(None, [f"model.init={init}", f"output.dir={out_dir}"])


def test_auto_init_prefers_triangulated_points_for_transforms_scenes(tmp_path, capsys):
    truth = load_scene(synthetic_dir("orbit"))
    shutil.copytree(synthetic_dir("orbit") / "images", tmp_path / "scene" / "images")
    save_transforms(truth.cameras, tmp_path / "scene" / "transforms.json")
    scene = load_scene(tmp_path / "scene", split="llff")
    assert scene.points is None
    xyz, rgb, source = initial_points(scene, _config(tmp_path / "run"))
    assert source.startswith("triangulated (") and len(xyz) > 300
    err = capsys.readouterr().err
    assert "triangulate [1/3] features" in err and "mean reprojection error" in err
    assert (tmp_path / "run" / "triangulation" / POINTS_FILE).is_file()
    # Points match what the scene's own SfM-style model says is there: within the true scene's bounds.
    lo, hi = truth.points.xyz.min(0) - 0.5, truth.points.xyz.max(0) + 0.5
    inside = np.all((xyz.numpy() >= lo) & (xyz.numpy() <= hi), axis=1)
    assert inside.mean() > 0.95


def test_llff_scene_without_points_triangulates(tmp_path):
    truth = load_scene(synthetic_dir("orbit"), split="all")
    views = list(range(12))  # 12 neighbouring views, 10 degrees apart
    (tmp_path / "images").mkdir()
    for v in views:
        shutil.copy(truth.files[v].image, tmp_path / "images" / truth.names[v])
    save_poses_bounds([truth.cameras[v] for v in views], tmp_path / "poses_bounds.npy", (1.0, 10.0))
    scene = load_scene(tmp_path, split="all")
    assert scene.source == "llff (images)" and scene.points is None
    xyz, _, source = initial_points(scene, _config(tmp_path / "run", "triangulate"))
    assert source.startswith("triangulated") and len(xyz) > 100


def test_textureless_scene_falls_back_to_random(tmp_path, capsys):
    """Flat grey images give no features: auto says why and uses random points; 'triangulate' raises."""
    cams = []
    for i in range(4):
        eye = (np.cos(i * 0.3) * 4, np.sin(i * 0.3) * 4, 1.0)
        cam = Camera(np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]), look_at(eye, (0, 0, 0)), 64, 48,
                     name=f"v{i}.png")
        (tmp_path / "scene" / "images").mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.full((48, 64, 3), 128, np.uint8)).save(tmp_path / "scene" / "images" / cam.name)
        cams.append(cam)
    save_transforms(cams, tmp_path / "scene" / "transforms.json")
    scene = load_scene(tmp_path / "scene")
    _, _, source = initial_points(scene, _config(tmp_path / "run"))
    assert source == "random"
    assert "using random points" in capsys.readouterr().err
    with pytest.raises(Exception, match="triangulat"):
        initial_points(scene, _config(tmp_path / "run2", "triangulate"))


def test_noise_pixels_do_not_break_it(tmp_path):
    """Unrelated noise images (no consistent geometry) give few or no points, never an exception in auto."""
    cams = []
    for i in range(3):
        cam = Camera(np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]), look_at((i * 0.2, -4, 0), (0, 0, 0)), 64,
                     48, name=f"n{i}.png")
        write_rgb(tmp_path / "scene" / "images" / cam.name, 64, 48, seed=i)
        cams.append(cam)
    save_transforms(cams, tmp_path / "scene" / "transforms.json")
    _, _, source = initial_points(load_scene(tmp_path / "scene"), _config(tmp_path / "run"))
    assert source == "random" or source.startswith("triangulated")


def test_every_run_finds_the_same_points(tmp_path):
    """Same images and poses, two runs on several threads: the same points (COLMAP's RANSAC is seeded, and images
    are numbered in view order, not in the order threaded feature extraction finished them)."""
    scene = load_scene(synthetic_dir("orbit"))
    runs = [triangulate_scene(scene, tmp_path / f"run{i}", num_threads=4, progress=False) for i in range(2)]
    assert not any(r.cached for r in runs) and len(runs[0].points) > 300
    a, b = (r.points for r in runs)
    np.testing.assert_array_equal(a.xyz, b.xyz)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    for v, (seen_a, seen_b) in enumerate(zip(a.observed_by, b.observed_by)):
        np.testing.assert_array_equal(seen_a, seen_b, err_msg=f"view {v}")


@pytest.mark.parametrize("found", [10, 50, 150])
def test_few_triangulated_points_are_kept_when_asked_for(tmp_path, monkeypatch, capsys, found):
    """auto wants MIN_TRIANGULATED_POINTS before it trusts triangulation over random points; model.init=triangulate
    (the few-view presets) keeps a few dozen (3 views of LLFF's leaves give 79) and fails only below the strict
    minimum."""
    from warpgs.data import PointCloud
    from warpgs.data.errors import SceneError
    from warpgs.data.sfm import init_points as ip
    from warpgs.data.sfm.triangulate import Triangulation

    rng = np.random.default_rng(0)
    cloud = PointCloud(rng.normal(size=(found, 3)).astype(np.float32), np.full((found, 3), 0.5, np.float32))
    monkeypatch.setattr("warpgs.data.sfm.triangulate.triangulate_scene",
                        lambda scene, cache_dir, **kw: Triangulation(cloud, 0.4, 0.1, False, {}))
    scene = load_scene(synthetic_dir("orbit"), split="llff")
    strict_ok = found >= ip.MIN_TRIANGULATED_POINTS_STRICT
    if strict_ok:
        assert len(ip.triangulated_points(scene, tmp_path, strict=True)[0]) == found
    else:
        with pytest.raises(SceneError, match=f"only {found} points.*model.init=auto"):
            ip.triangulated_points(scene, tmp_path, strict=True)
    # With the prior's points joining them (model.prior_points), the presets keep any number and say so.
    points, source = ip.triangulated_points(scene, tmp_path, strict=True, thin_ok=True)
    assert len(points) == found and (("the prior's points carry the start" in source) == (not strict_ok))
    auto = ip.triangulated_points(scene, tmp_path)
    assert (auto is not None) == (found >= ip.MIN_TRIANGULATED_POINTS)
    assert ("using random points" in capsys.readouterr().err) == (auto is None)


def test_a_later_run_on_the_same_capture_reads_the_shared_cache(tmp_path, monkeypatch, capsys):
    """The trainer caches triangulated points in $WARPGS_CACHE/triangulation too: a second run with a new output
    folder reads them (and keeps its own copy) instead of extracting and matching features again; another set of
    training views is another entry."""
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    truth = load_scene(synthetic_dir("orbit"), split="all")
    views = list(range(8))
    (tmp_path / "scene" / "images").mkdir(parents=True)
    for v in views:
        shutil.copy(truth.files[v].image, tmp_path / "scene" / "images" / truth.names[v])
    save_poses_bounds([truth.cameras[v] for v in views], tmp_path / "scene" / "poses_bounds.npy", (1.0, 10.0))
    scene = load_scene(tmp_path / "scene", split="all")
    first, _, source = initial_points(scene, _config(tmp_path / "run1", "triangulate"))
    assert "triangulate [1/3] features" in capsys.readouterr().err
    second, _, source2 = initial_points(scene, _config(tmp_path / "run2", "triangulate"))
    err = capsys.readouterr().err
    assert "features" not in err and "(cached)" in err and str(tmp_path / "cache") in err
    assert source2 == source and torch.equal(first, second)
    assert (tmp_path / "run2" / "triangulation" / POINTS_FILE).is_file()  # the run's own copy
    fewer = scene.with_split(views[:6], views[6:])
    initial_points(fewer, _config(tmp_path / "run3", "triangulate"))
    assert "triangulate [1/3] features" in capsys.readouterr().err
    assert len(list((tmp_path / "cache" / "triangulation").iterdir())) == 2
