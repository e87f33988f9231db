"""COLMAP models through pycolmap: round trips, splits, downscaling with a disk cache, undistortion."""
import os
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from data_fixtures import write_rgb
from warpgs.data import Camera, PointCloud, load_colmap, look_at, save_colmap
from warpgs.data.depth.align import sample_bilinear
from warpgs.data.formats.image_io import read_image


def _pycolmap_model(root: Path, binary: bool):
    """A model written by pycolmap's own API (not by our writer): two cameras (one distorted), three images,
    points with tracks."""
    rng = np.random.default_rng(0)
    rec = pycolmap.Reconstruction()
    cam1 = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 90.0, 64, 48)
    cam1.params = [90.0, 95.0, 31.0, 25.0]
    cam2 = pycolmap.Camera.create_from_model_name(2, "OPENCV", 80.0, 64, 48)
    cam2.params = [80.0, 82.0, 32.5, 23.5, -0.12, 0.03, 0.001, -0.002]
    rec.add_camera_with_trivial_rig(cam1)
    rec.add_camera_with_trivial_rig(cam2)
    xyz = rng.uniform(-0.5, 0.5, (20, 3))
    poses = {}
    for iid, (cam_id, eye) in enumerate([(1, (0, -3, 0.5)), (2, (1, -3, 0.2)), (1, (-1, -2.8, 0.0))], start=1):
        view = look_at(eye, (0, 0, 0))
        poses[f"img_{iid}.png"] = (view, cam_id)
        cam = rec.cameras[cam_id]
        kp = cam.img_from_cam((xyz @ view[:3, :3].T + view[:3, 3]))
        image = pycolmap.Image(name=f"img_{iid}.png", keypoints=kp, camera_id=cam_id, image_id=iid)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(view[:3, :4]))
        write_rgb(root / "images" / f"img_{iid}.png", 64, 48, seed=iid)
    for p in range(len(xyz)):
        track = pycolmap.Track()
        for iid in (1, 2, 3):
            if (p + iid) % 3:  # every point seen by two of the three images
                track.add_element(iid, p)
        rec.add_point3D(xyz[p], track, np.array([p * 10, 255 - p * 10, 7], dtype=np.uint8))
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (rec.write if binary else rec.write_text)(str(model))
    return rec, xyz, poses


@pytest.mark.parametrize("binary", [False, True])
def test_pycolmap_model_round_trip(tmp_path, binary):
    rec, xyz, poses = _pycolmap_model(tmp_path, binary)
    assert (tmp_path / "sparse/0" / ("cameras.bin" if binary else "cameras.txt")).is_file()
    scene = load_colmap(tmp_path, undistort=False)
    assert scene.names == ["img_1.png", "img_2.png", "img_3.png"]
    for cam in scene.cameras:
        view, cam_id = poses[cam.name]
        np.testing.assert_allclose(cam.viewmat, view, atol=1e-9)
        ref = rec.cameras[cam_id]
        np.testing.assert_allclose(cam.K, ref.calibration_matrix(), atol=1e-12)
        assert (cam.width, cam.height) == (64, 48)
    assert scene.cameras[0].model == "PINHOLE" and not scene.cameras[0].has_distortion
    assert scene.cameras[1].model == "OPENCV"
    np.testing.assert_allclose(scene.cameras[1].distortion, [-0.12, 0.03, 0.001, -0.002])
    np.testing.assert_allclose(scene.points.xyz, xyz, atol=1e-6)
    np.testing.assert_allclose(scene.points.rgb[:, 2], 7 / 255)
    for i, iid in enumerate((1, 2, 3)):
        expected = [p for p in range(len(xyz)) if (p + iid) % 3]
        assert scene.points.observed_by[i].tolist() == expected and scene.visible_points(i).tolist() == expected
    # Projection of our camera (with distortion) agrees with pycolmap's own.
    for i, iid in enumerate((1, 2, 3)):
        ours, _ = scene.cameras[i].project(xyz)
        theirs = np.array([rec.images[iid].project_point(p) for p in xyz])
        np.testing.assert_allclose(ours, theirs, atol=1e-6)


def test_our_writer_round_trips(tmp_path):
    cams = [Camera(np.array([[100, 0, 40.5], [0, 101, 30.25], [0, 0, 1]]), look_at((x, -4, 1), (0, 0, 0)), 80, 60,
                   name=f"v{k}.png") for k, x in enumerate((-1.0, 0.0, 1.0))]
    radial_K = np.array([[100, 0, 40.5], [0, 100, 30.25], [0, 0, 1]])  # RADIAL has one focal length
    cams.append(Camera(radial_K, look_at((0, -5, 2), (0, 0, 0)), 80, 60, name="d.png", model="RADIAL",
                       distortion=(0.05, -0.01)))
    pts = PointCloud(np.random.default_rng(1).normal(size=(30, 3)) * 0.3, np.random.default_rng(2).uniform(size=(30, 3)),
                     [np.arange(0, 30, 2), np.arange(1, 30, 2), np.arange(30), np.zeros(0, int)])
    save_colmap(cams, tmp_path / "sparse/0", pts, binary=True)
    for c in cams:
        write_rgb(tmp_path / "images" / c.name, 80, 60)
    scene = load_colmap(tmp_path, undistort=False)
    for a, b in zip(sorted(cams, key=lambda c: c.name), scene.cameras):
        assert a.name == b.name and a.model == b.model
        np.testing.assert_allclose(a.K, b.K, atol=1e-12)
        np.testing.assert_allclose(a.viewmat, b.viewmat, atol=1e-9)
        np.testing.assert_allclose(a.distortion, b.distortion)
    np.testing.assert_allclose(scene.points.rgb, np.round(pts.rgb * 255) / 255, atol=1e-6)
    by_name = {c.name: i for i, c in enumerate(cams)}
    for i, name in enumerate(scene.names):
        assert scene.points.observed_by[i].tolist() == sorted(pts.observed_by[by_name[name]].tolist())
    # A view without track observations falls back to the points that project into it.
    d = scene.index("d.png")
    pix, z = scene.cameras[d].project(scene.points.xyz)
    assert scene.visible_points(d).tolist() == np.nonzero((z > 0) & (pix[:, 0] >= 0) & (pix[:, 0] < 80)
                                                          & (pix[:, 1] >= 0) & (pix[:, 1] < 60))[0].tolist()


def test_split_file_and_llff(tmp_path):
    _pycolmap_model(tmp_path, binary=False)
    (tmp_path / "split.json").write_text('{"train": ["img_1.png", "img_3.png"], "test": ["img_2.png"]}')
    scene = load_colmap(tmp_path)
    assert scene.train == [0, 2] and scene.test == [1]
    assert load_colmap(tmp_path, split="llff").test == [0]
    assert load_colmap(tmp_path, split="all").train == [0, 1, 2]


def test_few_view_scene_gets_no_all_view_points(tmp_path):
    # The model's points were triangulated with every view: a few-view run (n_train) must not start from them.
    _pycolmap_model(tmp_path, binary=True)
    assert load_colmap(tmp_path).points is not None and len(load_colmap(tmp_path).points) > 0
    few = load_colmap(tmp_path, split="llff", n_train=1)
    assert few.points is None and len(few.train) == 1


@pytest.mark.parametrize("factor", [2, 4, 8])
def test_downscale_area_average_and_disk_cache(tmp_path, monkeypatch, factor):
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    _pycolmap_model(tmp_path, binary=False)
    full = load_colmap(tmp_path, undistort=False)
    small = full.downscaled(factor)
    cam, big = small.cameras[0], full.cameras[0]
    assert (cam.width, cam.height) == (64 // factor, 48 // factor)
    np.testing.assert_allclose(cam.K[:2], big.K[:2] / factor)
    img = small.image(0)
    assert img.shape == (48 // factor, 64 // factor, 3) and img.dtype == torch.float32
    ref = read_image(tmp_path / "images/img_1.png")[0]
    blocks = ref.reshape(48 // factor, factor, 64 // factor, factor, 3).mean((1, 3))
    np.testing.assert_allclose(img.numpy(), blocks, atol=0.5 / 255 + 1e-6)  # 8-bit cache quantisation
    cached = list((tmp_path / "cache" / "images").rglob("*.png"))
    assert len(cached) == 1
    # A fresh scene object is served from the cache: plant a marker there and it comes back.
    marker = np.full((48 // factor, 64 // factor, 3), 77, np.uint8)
    Image.fromarray(marker).save(cached[0])
    again = load_colmap(tmp_path, undistort=False).downscaled(factor)
    np.testing.assert_allclose(again.image(0).numpy(), 77 / 255, atol=1e-6)
    # Editing the source image invalidates its cache entry.
    write_rgb(tmp_path / "images/img_1.png", 64, 48, seed=99)
    fresh = load_colmap(tmp_path, undistort=False).downscaled(factor).image(0).numpy()
    ref = read_image(tmp_path / "images/img_1.png")[0]
    np.testing.assert_allclose(fresh, ref.reshape(48 // factor, factor, 64 // factor, factor, 3).mean((1, 3)),
                               atol=0.5 / 255 + 1e-6)


def test_a_cached_image_read_again_is_marked_used(tmp_path, monkeypatch):
    # warpgs-cache --max-gb drops the least recently used entries: a read must renew the entry's time.
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    _pycolmap_model(tmp_path, binary=False)
    load_colmap(tmp_path, undistort=False).downscaled(2).image(0)
    (cached,) = list((tmp_path / "cache" / "images").rglob("*.png"))
    old = time.time() - 7 * 86400
    os.utime(cached, (old, old))
    load_colmap(tmp_path, undistort=False).downscaled(2).image(0)
    assert cached.stat().st_mtime > old + 86400


def test_undistortion_matches_pycolmap(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    _pycolmap_model(tmp_path, binary=False)
    # A smooth test image, so interpolation differences between implementations stay small.
    v, u = np.mgrid[0:48, 0:64]
    rgb = np.stack([np.sin(u / 5.0), np.cos(v / 4.0), np.sin((u + v) / 7.0)], -1) * 0.5 + 0.5
    Image.fromarray((rgb * 255).round().astype(np.uint8)).save(tmp_path / "images/img_2.png")
    scene = load_colmap(tmp_path)  # undistorts by default
    i = scene.index("img_2.png")
    cam = scene.cameras[i]
    assert cam.model == "PINHOLE" and not cam.has_distortion
    distorted = scene.native_cameras[i].to_pycolmap()
    bitmap = pycolmap.Bitmap.from_array(np.array(Image.open(tmp_path / "images/img_2.png")))
    theirs_bitmap, theirs_cam = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), bitmap, distorted)
    assert (cam.width, cam.height) == (theirs_cam.width, theirs_cam.height)
    np.testing.assert_allclose(cam.K, theirs_cam.calibration_matrix(), atol=1e-9)
    ours = scene.image(i).numpy()
    theirs = theirs_bitmap.to_array().astype(np.float32) / 255.0
    assert np.abs(ours - theirs).mean() < 0.004  # measured 0.001 (8-bit rounding); naive resize: 0.02
    # Geometry: the map sends the undistorted projection of a world point to its distorted projection.
    pts = np.random.default_rng(3).uniform(-0.4, 0.4, (200, 3))
    pix_undist, _ = cam.project(pts)
    pix_dist, _ = scene.native_cameras[i].project(pts)
    umap = scene._undistort_map(i)
    valid = np.ones(umap.source_xy.shape[:2], bool)
    sx, ok_x = sample_bilinear(umap.source_xy[..., 0], valid, pix_undist)
    sy, ok_y = sample_bilinear(umap.source_xy[..., 1], valid, pix_undist)
    ok = ok_x & ok_y
    assert ok.sum() > 50
    np.testing.assert_allclose(np.stack([sx, sy], -1)[ok], pix_dist[ok], atol=0.02)
