"""LLFF folders (poses_bounds.npy + images/ + images_N/): the pose convention, images_N choice, split, errors."""
import shutil
from pathlib import Path

import numpy as np
import pytest

from data_fixtures import write_rgb
from warpgs.data import Camera, PointCloud, SceneError, detect_format, load_scene, look_at, save_colmap
from warpgs.data.formats.llff import (POSES_FILE, llff_from_viewmat, load_llff, read_poses_bounds,
                                      save_poses_bounds, viewmat_from_llff)
from warpgs.data.formats.splits import write_split_file
from warpgs.data.formats.image_io import read_image
from warpgs.data.sfm.sim3 import pose_errors

W, H, F = 64, 48, 55.0
REAL = Path(__file__).resolve().parents[1] / "data"


def _cameras(n=10, seed=0):
    """Forward-facing cameras (LLFF's kind of capture) with our own intrinsics and poses."""
    rng = np.random.default_rng(seed)
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
    cams = []
    for i in range(n):
        eye = np.array([rng.uniform(-1, 1), -4.0 + rng.uniform(-0.3, 0.3), rng.uniform(-0.6, 0.6)])
        target = rng.normal(scale=0.2, size=3)
        cams.append(Camera(K, look_at(eye, target), W, H, name=f"IMG_{100 + i}.JPG"))
    return cams


def _llff_folder(root: Path, cams, shipped=(), shipped_names="same"):
    for i, cam in enumerate(cams):
        write_rgb(root / "images" / cam.name, cam.width, cam.height, seed=i)
        for f in shipped:
            name = cam.name if shipped_names == "same" else f"image{i:03d}.png"
            write_rgb(root / f"images_{f}" / name, cam.width // f, cam.height // f, seed=100 * f + i)
    save_poses_bounds(cams, root / POSES_FILE, np.tile([1.5, 9.0], (len(cams), 1)) + np.arange(len(cams))[:, None])
    return root


def test_llff_matrix_is_down_right_back():
    """A hand-written LLFF pose (not our writer's): down = world -y, right = world +x, back = world +z. A point at
    world (0, 0, -5) is then straight ahead, +x is to the right of the image, +y is up (smaller pixel rows)."""
    pose = np.array([[0.0, 1.0, 0.0, 0.0, H], [-1.0, 0.0, 0.0, 0.0, W], [0.0, 0.0, 1.0, 0.0, F]])
    cam = Camera(np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]]), viewmat_from_llff(pose), W, H)
    pix, z = cam.project(np.array([[0.0, 0.0, -5.0], [1.0, 0.0, -5.0], [0.0, 1.0, -5.0]]))
    np.testing.assert_allclose(pix[0], [W / 2, H / 2], atol=1e-9)
    assert z[0] == pytest.approx(5.0)
    assert pix[1, 0] > W / 2 + 5 and abs(pix[1, 1] - H / 2) < 1e-9
    assert pix[2, 1] < H / 2 - 5 and abs(pix[2, 0] - W / 2) < 1e-9
    np.testing.assert_allclose(llff_from_viewmat(cam.viewmat, H, W, F), pose, atol=1e-12)


def test_round_trip_gives_our_cameras_back(tmp_path):
    cams = _cameras()
    _llff_folder(tmp_path, cams)
    assert detect_format(tmp_path) == "llff"
    scene = load_scene(tmp_path)
    assert scene.source == "llff (images)"
    assert scene.names == [c.name for c in cams]
    for got, want in zip(scene.cameras, cams):
        np.testing.assert_allclose(got.viewmat, want.viewmat, atol=1e-12)
        np.testing.assert_allclose(got.K, want.K, atol=1e-12)
        assert (got.width, got.height, got.model) == (W, H, "PINHOLE")
    assert scene.test == [0, 8] and scene.train == [1, 2, 3, 4, 5, 6, 7, 9]  # LLFF protocol by default
    near_far = np.array(scene.metadata["near_far"])
    np.testing.assert_allclose(near_far[3], [4.5, 12.0])
    vm, hwf, bounds = read_poses_bounds(tmp_path / POSES_FILE)
    np.testing.assert_allclose(hwf, np.tile([H, W, F], (10, 1)))


def test_split_options(tmp_path):
    cams = _cameras(n=17)
    _llff_folder(tmp_path, cams)
    scene = load_scene(tmp_path, split="llff", n_train=3)
    assert scene.test == [0, 8, 16] and scene.train == [1, 7, 15]  # rest[round(linspace(0, 13, 3))]
    assert load_scene(tmp_path, split="all").test == []
    write_split_file(tmp_path / "split.json", [c.name for c in cams], [2, 3], [5])
    scene = load_scene(tmp_path)
    assert (scene.train, scene.test) == ([2, 3], [5])


@pytest.mark.parametrize("names", ["same", "renamed"])
def test_images_n_is_used_for_its_downscale(tmp_path, names):
    cams = _cameras()
    _llff_folder(tmp_path, cams, shipped=(2,), shipped_names=names)
    scene = load_scene(tmp_path, downscale=2)
    assert scene.source == "llff (images_2)" and scene.downscale == 1
    assert scene.names == [c.name for c in cams]  # names stay those of images/, whatever images_2 calls them
    cam = scene.cameras[4]
    assert (cam.width, cam.height) == (W // 2, H // 2)
    np.testing.assert_allclose(cam.K, np.array([[F / 2, 0, W / 4], [0, F / 2, H / 4], [0, 0, 1]]), atol=1e-12)
    np.testing.assert_allclose(cam.viewmat, cams[4].viewmat, atol=1e-12)
    shipped = tmp_path / "images_2" / (cams[4].name if names == "same" else "image004.png")
    assert scene.files[4].image == shipped
    np.testing.assert_array_equal(scene.image_np(4)[0], read_image(shipped)[0])


def test_images_n_alone_is_enough_for_its_downscale(tmp_path):
    # A copy trimmed to the resolution in use (no images/): the poses' hwf gives the scale.
    cams = _cameras()
    _llff_folder(tmp_path, cams, shipped=(4,), shipped_names="renamed")
    shutil.rmtree(tmp_path / "images")
    scene = load_scene(tmp_path, downscale=4)
    assert scene.source == "llff (images_4)" and scene.downscale == 1 and len(scene) == len(cams)
    np.testing.assert_allclose(scene.cameras[3].K[0, 0], F / 4, rtol=1e-12)
    with pytest.raises(FileNotFoundError, match="images.*full-resolution"):
        load_scene(tmp_path, downscale=2)  # neither images/ nor images_2/


def test_missing_or_incomplete_images_n_resizes_images(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    cams = _cameras()
    _llff_folder(tmp_path / "s", cams, shipped=(2,), shipped_names="renamed")
    (tmp_path / "s" / "images_2" / "image009.png").unlink()  # like beer's images_8: only some views
    for factor in (2, 4):
        scene = load_scene(tmp_path / "s", downscale=factor)
        assert scene.source == "llff (images)" and scene.downscale == factor
        cam = scene.cameras[0]
        assert (cam.width, cam.height) == (W // factor, H // factor)
        assert cam.fx == pytest.approx(F / factor)
        assert scene.image_np(0)[0].shape == (H // factor, W // factor, 3)
    assert any((tmp_path / "cache").rglob("*.png"))  # resized through the image cache


def test_masks_keep_full_size_cameras(tmp_path, monkeypatch):
    """Per-view maps are checked against the stored cameras, so with full-size masks images/ is resized."""
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    cams = _cameras(n=3)
    _llff_folder(tmp_path, cams, shipped=(2,))
    for cam in cams:
        write_rgb(tmp_path / "masks" / (Path(cam.name).stem + ".png"), W, H)
    scene = load_scene(tmp_path, downscale=2)
    assert scene.source == "llff (images)" and scene.mask_np(0).shape == (H // 2, W // 2)


def test_points_come_from_an_agreeing_colmap_model(tmp_path):
    cams = _cameras(n=4)
    _llff_folder(tmp_path, cams)
    xyz = np.random.default_rng(1).normal(scale=0.3, size=(30, 3))
    save_colmap(cams, tmp_path / "sparse" / "0", PointCloud(xyz, np.full((30, 3), 0.5), [np.arange(30)] * 4))
    scene = load_scene(tmp_path)
    assert scene.source.startswith("llff") and len(scene.points) == 30
    assert load_scene(tmp_path, format="colmap").source == "colmap"
    # A model in another frame (here: shifted) is not the poses' model: its points are not used.
    moved = []
    for c in cams:
        view = c.viewmat.copy()
        view[:3, 3] += [0.5, 0.0, 0.0]
        moved.append(Camera(c.K, view, W, H, name=c.name))
    shutil.rmtree(tmp_path / "sparse")
    save_colmap(moved, tmp_path / "sparse" / "0", PointCloud(xyz, np.full((30, 3), 0.5), [np.arange(30)] * 4))
    assert load_scene(tmp_path).points is None


def test_rows_follow_registered_names_when_images_has_extras(tmp_path):
    cams = _cameras(n=4)
    _llff_folder(tmp_path, cams)
    write_rgb(tmp_path / "images" / "IMG_000_unregistered.JPG", W, H)
    with pytest.raises(SceneError, match="4 poses but 5 images"):
        load_scene(tmp_path)
    save_colmap(cams, tmp_path / "sparse" / "0")
    assert load_scene(tmp_path).names == [c.name for c in cams]


def test_errors_name_the_file(tmp_path):
    cams = _cameras(n=3)
    _llff_folder(tmp_path, cams)
    poses = tmp_path / POSES_FILE
    np.save(poses, np.zeros((3, 15)))
    with pytest.raises(SceneError, match=r"poses_bounds\.npy.*\[N, 17\]"):
        load_scene(tmp_path)
    poses.write_bytes(b"not numpy")
    with pytest.raises(SceneError, match=r"poses_bounds\.npy.*unreadable"):
        load_scene(tmp_path)
    save_poses_bounds(cams, poses, (1.0, 5.0))
    write_rgb(tmp_path / "images" / cams[1].name, W, W)  # 64x64: not a scaled 64x48 image
    with pytest.raises(SceneError, match=r"poses_bounds\.npy.*view 1"):
        load_scene(tmp_path)
    with pytest.raises(ValueError, match="principal point"):
        save_poses_bounds([Camera(np.array([[F, 0, 10], [0, F, H / 2], [0, 0, 1]]), np.eye(4), W, H)], poses, (1, 2))


@pytest.mark.skipif(not (REAL / "beer" / POSES_FILE).is_file() or not (REAL / "beer" / "sparse/0/images.bin").is_file(),
                    reason="real LLFF capture data/beer not present (git-ignored)")
def test_real_llff_poses_match_their_colmap_model():
    """data/beer ships both: its poses_bounds.npy was made from sparse/0, so the two agree exactly."""
    llff = load_scene(REAL / "beer", downscale=8, split="all")
    ref = load_scene(REAL / "beer", format="colmap", downscale=8, split="all")
    assert llff.names == ref.names and len(llff) == 71
    errors = pose_errors(llff.cameras, [ref.cameras[ref.index(n)] for n in llff.names])
    assert errors["max_rotation_deg"] < 1e-4 and abs(errors["scale"] - 1) < 1e-9
    assert max(np.abs(a.viewmat - b.viewmat).max() for a, b in zip(llff.cameras, ref.cameras)) < 1e-6
    assert llff.points is not None and len(llff.points) == len(ref.points)
