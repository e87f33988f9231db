"""transforms.json (OpenGL poses, shared/per-frame intrinsics, distortion) against its COLMAP equivalent."""
import json

import numpy as np
import pycolmap
import pytest
from PIL import Image

from data_fixtures import write_rgb
from warpgs.data import initial_points, load_colmap, load_scene, load_transforms, look_at, save_transforms

W, H = 96, 72
FX, FY, CX, CY = 80.0, 83.0, 47.3, 36.1
K1, K2, P1, P2 = -0.15, 0.04, 0.002, -0.003


def _poses():
    eyes = [(0.0, -3.0, 1.0), (1.5, -2.5, 0.8), (-1.2, -2.7, 1.4), (0.3, -3.2, -0.5)]
    return [look_at(e, (0.1, 0.0, 0.2)) for e in eyes]


def _opengl_c2w(viewmat):
    """Written out independently of the library: invert the pose, then flip the camera's y and z axes."""
    c2w = np.linalg.inv(viewmat)
    return c2w @ np.diag([1.0, -1.0, -1.0, 1.0])


def _opencv_project(points_cam):
    """OpenCV's radial-tangential model, as documented for cv::projectPoints (k1, k2, p1, p2)."""
    x, y = points_cam[:, 0] / points_cam[:, 2], points_cam[:, 1] / points_cam[:, 2]
    r2 = x * x + y * y
    radial = 1 + K1 * r2 + K2 * r2 * r2
    xd = x * radial + 2 * P1 * x * y + P2 * (r2 + 2 * x * x)
    yd = y * radial + P1 * (r2 + 2 * y * y) + 2 * P2 * x * y
    return np.stack([FX * xd + CX, FY * yd + CY], -1)


@pytest.fixture
def twin_scenes(tmp_path):
    """The same four distorted cameras as transforms.json (shared intrinsics) and as a pycolmap-written model."""
    views = _poses()
    names = [f"frame_{k:02d}.png" for k in range(len(views))]
    for k, n in enumerate(names):
        write_rgb(tmp_path / "ns" / "images" / n, W, H, seed=k)
        write_rgb(tmp_path / "cm" / "images" / n, W, H, seed=k)
    frames = [{"file_path": f"images/{n}", "transform_matrix": _opengl_c2w(v).tolist()} for n, v in zip(names, views)]
    meta = {"camera_model": "OPENCV", "fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY, "w": W, "h": H,
            "k1": K1, "k2": K2, "p1": P1, "p2": P2, "frames": frames}
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, "OPENCV", FX, W, H)
    cam.params = [FX, FY, CX, CY, K1, K2, P1, P2]
    rec.add_camera_with_trivial_rig(cam)
    for k, (n, v) in enumerate(zip(names, views), start=1):
        rec.add_image_with_trivial_frame(pycolmap.Image(name=n, camera_id=1, image_id=k), pycolmap.Rigid3d(v[:3, :4]))
    (tmp_path / "cm" / "sparse" / "0").mkdir(parents=True)
    rec.write_text(str(tmp_path / "cm" / "sparse" / "0"))
    return tmp_path / "ns", tmp_path / "cm", rec, views


def test_distorted_transforms_reprojects_like_colmap(twin_scenes):
    ns_root, cm_root, rec, views = twin_scenes
    ns = load_transforms(ns_root, undistort=False)
    cm = load_colmap(cm_root, undistort=False)
    assert [c.name for c in ns.cameras] == [f"images/{c.name}" for c in cm.cameras]
    pts = np.random.default_rng(0).uniform(-0.6, 0.6, (300, 3)) + [0.1, 0.0, 0.2]
    worst = 0.0
    for k, (a, b) in enumerate(zip(ns.cameras, cm.cameras)):
        assert a.model == "OPENCV" and np.allclose(a.distortion, (K1, K2, P1, P2))
        pa, za = a.project(pts)
        pb, zb = b.project(pts)
        inside = (za > 0) & (pb[:, 0] > 0) & (pb[:, 0] < W) & (pb[:, 1] > 0) & (pb[:, 1] < H)
        assert inside.sum() > 100
        worst = max(worst, np.abs(pa[inside] - pb[inside]).max())
        # Both agree with pycolmap's projection and with OpenCV's published model.
        theirs = np.array([rec.images[k + 1].project_point(p) for p in pts[inside]])
        np.testing.assert_allclose(pa[inside], theirs, atol=1e-6)
        cam_pts = pts[inside] @ views[k][:3, :3].T + views[k][:3, 3]
        np.testing.assert_allclose(pa[inside], _opencv_project(cam_pts), atol=1e-6)
    assert worst < 0.5
    print(f"transforms.json vs COLMAP: max reprojection difference {worst:.2e} px")


def test_undistorted_twins_agree(twin_scenes, tmp_path, monkeypatch):
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    ns_root, cm_root, _, _ = twin_scenes
    ns, cm = load_transforms(ns_root), load_colmap(cm_root)
    pts = np.random.default_rng(1).uniform(-0.5, 0.5, (200, 3))
    for i, (a, b) in enumerate(zip(ns.cameras, cm.cameras)):
        assert a.model == b.model == "PINHOLE"
        assert (a.width, a.height) == (b.width, b.height)
        np.testing.assert_allclose(a.project(pts)[0], b.project(pts)[0], atol=0.5)
        np.testing.assert_allclose(ns.image(i).numpy(), cm.image(i).numpy(), atol=1e-6)


def test_nerf_synthetic_layout(tmp_path):
    """transforms_train/test.json, camera_angle_x only, file paths without extension, RGBA over a background."""
    angle = 0.69
    rgba = np.zeros((40, 40, 4), np.uint8)
    rgba[10:30, 10:30] = [255, 0, 0, 255]
    for part, count in (("train", 3), ("test", 2)):
        frames = []
        for k in range(count):
            (tmp_path / part).mkdir(exist_ok=True)
            Image.fromarray(rgba).save(tmp_path / part / f"r_{k}.png")
            view = look_at((np.cos(k), np.sin(k), 0.5), (0, 0, 0))
            frames.append({"file_path": f"./{part}/r_{k}", "transform_matrix": _opengl_c2w(view).tolist()})
        (tmp_path / f"transforms_{part}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    scene = load_scene(tmp_path, background=(1.0, 1.0, 1.0))
    assert scene.source == "transforms" and len(scene) == 5
    assert [scene.names[i] for i in scene.train] == ["train/r_0.png", "train/r_1.png", "train/r_2.png"]
    assert [scene.names[i] for i in scene.test] == ["test/r_0.png", "test/r_1.png"]
    cam = scene.cameras[0]
    assert cam.fx == pytest.approx(20.0 / np.tan(angle / 2)) and cam.fy == cam.fx
    assert (cam.cx, cam.cy) == (20.0, 20.0)
    img = scene.image(0).numpy()
    np.testing.assert_allclose(img[0, 0], [1, 1, 1])  # transparent -> background
    np.testing.assert_allclose(img[20, 20], [1, 0, 0])
    view = scene.view(0)
    assert view.mask is not None and view.mask[0, 0, 0].item() is False and view.mask[20, 20, 0].item() is True
    # No SfM points here: initialisation falls back to random points in front of the training cameras.
    points, origin = initial_points(scene, n=500)
    assert origin == "random" and len(points) == 500
    seen = np.zeros(500, bool)
    for i in scene.train:  # every point was drawn inside some training camera's frustum
        pix, z = scene.cameras[i].project(points.xyz)
        seen |= (z > 0) & (pix[:, 0] >= -1e-6) & (pix[:, 0] <= 40 + 1e-6) & (pix[:, 1] >= -1e-6) & (pix[:, 1] <= 40 + 1e-6)
    assert seen.all()


def test_save_transforms_round_trip(twin_scenes, tmp_path):
    ns_root, _, _, _ = twin_scenes
    ns = load_transforms(ns_root, undistort=False)
    out = tmp_path / "again"
    (out / "images").mkdir(parents=True)
    for c in ns.cameras:
        write_rgb(out / c.name, W, H)
    save_transforms([c for c in ns.cameras], out / "transforms.json", image_prefix="")
    again = load_transforms(out, undistort=False)
    for a, b in zip(ns.cameras, again.cameras):
        np.testing.assert_allclose(a.viewmat, b.viewmat, atol=1e-9)
        np.testing.assert_allclose(a.K, b.K)
        assert a.model == b.model and np.allclose(a.distortion, b.distortion)
