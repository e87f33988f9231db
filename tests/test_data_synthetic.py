"""The built-in synthetic scene: exact geometry, labels, SfM-like points, layout, caching, trainer tensors."""
import json
import time

import numpy as np
import pytest
import torch

from data_fixtures import GENERATION_SECONDS, default_lightfield, synthetic_dir
from warpgs.data import default_scene, load_scene
from warpgs.data.formats.raytrace import Box, Plane, Sphere
from warpgs.data.formats.synthetic import scene_definition


def _surface_distance(obj, p):
    """Distance of points to the surface of a scene primitive, computed from its definition."""
    if isinstance(obj, Sphere):
        return np.abs(np.linalg.norm(p - np.asarray(obj.center), axis=1) - obj.radius)
    if isinstance(obj, Plane):
        return np.abs(p[:, 2] - obj.z)
    if isinstance(obj, Box):
        local = (p - np.asarray(obj.center)) @ obj._rot
        q = np.abs(local) - np.asarray(obj.half)
        outside = np.linalg.norm(np.maximum(q, 0), axis=1)
        return np.abs(outside + np.minimum(q.max(axis=1), 0))
    raise TypeError(obj)


def _unproject(cam, depth):
    v, u = np.mgrid[0:cam.height, 0:cam.width] + 0.5
    pts = np.stack([(u - cam.cx) / cam.fx * depth, (v - cam.cy) / cam.fy * depth, depth], -1).reshape(-1, 3)
    return (pts - cam.viewmat[:3, 3]) @ cam.viewmat[:3, :3]


@pytest.mark.parametrize("kind", ["lightfield", "orbit"])
def test_depth_labels_normals_are_exact(kind):
    scene = load_scene(synthetic_dir(kind))
    print(f"{kind}: generated {len(scene)} views at 128x96 in {GENERATION_SECONDS.get(kind, 0):.2f} s")
    objects = scene_definition().objects
    assert scene.label_names == {i + 1: o.name for i, o in enumerate(objects)}
    assert "red sphere" in scene.label_names.values()
    for i in range(0, len(scene), 3):
        depth, valid = scene.depth_np(i)
        labels = scene.labels_np(i)
        finite = np.isfinite(depth) & valid
        assert ((labels == 0) == ~finite).all()  # sky has no depth and no label
        pts = _unproject(scene.cameras[i], np.where(finite, depth, 1.0).astype(np.float64))
        for obj_id in np.unique(labels[finite]):
            sel = (labels == obj_id).ravel() & finite.ravel()
            err = _surface_distance(objects[obj_id - 1], pts[sel])
            assert err.max() < 2e-5 * depth[finite].max(), (scene.names[i], objects[obj_id - 1].name, err.max())


def test_normals_are_unit_and_face_the_camera():
    from warpgs.data.depth.files import read_exr_channels

    root = synthetic_dir("lightfield")
    scene = load_scene(root)
    n = read_exr_channels(root / "normals" / "r1_c1.exr")["N"]
    labels = scene.labels_np(scene.index("r1_c1.png"))
    hit = labels > 0
    np.testing.assert_allclose(np.linalg.norm(n[hit], axis=1), 1.0, atol=1e-5)
    assert (n[~hit] == 0).all()
    cam = scene.cameras[scene.index("r1_c1.png")]
    v, u = np.nonzero(hit)
    rays = np.stack([(u + 0.5 - cam.cx) / cam.fx, (v + 0.5 - cam.cy) / cam.fy, np.ones_like(u, float)], -1)
    assert (np.einsum("ij,ij->i", rays @ cam.viewmat[:3, :3], n[hit]) < 0).all()


def test_sfm_like_points_lie_on_surfaces_and_tracks_are_true():
    scene = load_scene(synthetic_dir("lightfield"))
    objects = scene_definition().objects
    pts = scene.points.xyz.astype(np.float64)
    nearest = np.min(np.stack([_surface_distance(o, pts) for o in objects]), axis=0)
    assert len(pts) == 3000 and nearest.max() < 1e-4
    for i in scene.train:
        seen = scene.visible_points(i)
        assert len(seen) > 500
        pix, z = scene.cameras[i].project(scene.points.xyz[seen])
        depth, _ = scene.depth_np(i)
        d = depth[np.floor(pix[:, 1]).astype(int), np.floor(pix[:, 0]).astype(int)]
        assert (np.abs(d - z) < 0.01 * z).all()
    assert all(len(scene.points.observed_by[i]) == 0 for i in scene.test)  # test views contribute no points
    assert all(len(scene.visible_points(i)) > 500 for i in scene.test)  # ...but see many (by projection)


def test_layout_and_protocols():
    lf = load_scene(synthetic_dir("lightfield"))
    assert lf.source == "lightfield" and len(lf.train) == 9 and len(lf.test) == 4
    positions = lf.metadata["grid_positions"]
    assert sorted(positions[lf.names[i]] for i in lf.train) == [(r, c) for r in (0.0, 1.0, 2.0) for c in (0.0, 1.0, 2.0)]
    # Parallel optical axes, sub-apertures one baseline apart along the image axes.
    centre = lf.cameras[lf.index("r1_c1.png")]
    right = lf.cameras[lf.index("r1_c2.png")]
    np.testing.assert_allclose(right.viewmat[:3, :3], centre.viewmat[:3, :3], atol=1e-12)
    np.testing.assert_allclose(centre.world_to_camera(right.center[None])[0], [0.3, 0, 0], atol=1e-9)
    orbit = load_scene(synthetic_dir("orbit"))
    assert orbit.source == "colmap" and len(orbit) == 36
    assert orbit.test == [0, 8, 16, 24, 32] and len(orbit.train) == 31
    meta = json.loads((synthetic_dir("orbit") / "synthetic.json").read_text())
    assert meta["kind"] == "orbit" and meta["settings"]["width"] == 128


def test_trainer_view_tensors():
    scene = load_scene(synthetic_dir("lightfield"))
    v = scene.view(scene.train[0])
    assert v.viewmat.shape == (4, 4) and v.viewmat.dtype == torch.float32
    assert v.K.shape == (3, 3) and v.K.dtype == torch.float32
    assert v.image.shape == (96, 128, 3) and v.image.dtype == torch.float32
    assert 0.0 <= v.image.min().item() and v.image.max().item() <= 1.0
    assert v.labels.shape == (96, 128) and v.labels.dtype == torch.int64
    assert v.depth.shape == (96, 128, 1)
    assert v.inv_depth_prior is None  # no priors until they are computed
    # The trainer's K and viewmat project a known surface point onto its pixel.
    depth, _ = scene.depth_np(v.index)
    assert np.isfinite(depth[40, 70])
    p = _unproject(scene.cameras[v.index], np.where(np.isfinite(depth), depth, 1.0).astype(np.float64))[40 * 128 + 70]
    cam = v.K.double() @ (v.viewmat.double()[:3, :3] @ torch.tensor(p) + v.viewmat.double()[:3, 3])
    np.testing.assert_allclose((cam[:2] / cam[2]).numpy(), [70.5, 40.5], atol=1e-3)


def test_downscaled_synthetic_scene_keeps_labels_and_depth_consistent(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path))
    scene = load_scene(synthetic_dir("lightfield")).downscaled(4)
    v = scene.view(scene.train[4])
    assert v.image.shape == (24, 32, 3) and v.labels.shape == (24, 32) and v.depth.shape == (24, 32, 1)
    full = load_scene(synthetic_dir("lightfield"))
    big = full.labels_np(scene.train[4])
    # Centre sampling: each coarse label is the fine label at the centre of its 4x4 block.
    np.testing.assert_array_equal(v.labels.numpy(), big[2::4, 2::4])


def test_default_scene_is_generated_once(monkeypatch):
    path, seconds, cache = default_lightfield()
    print(f"default_scene(): light field with depth priors generated in {seconds:.2f} s")
    assert seconds < 60  # a few seconds on an idle machine; only catches pathological slow-downs here
    assert path.parent == cache / "synthetic" and (path / "synthetic.json").is_file()
    assert not [p for p in (cache / "synthetic").iterdir() if p.name.startswith(".")]  # no leftovers
    stamp = (path / "synthetic.json").stat().st_mtime_ns
    monkeypatch.setenv("WARPGS_CACHE", str(cache))
    start = time.perf_counter()
    assert default_scene() == path
    assert time.perf_counter() - start < 0.1 and (path / "synthetic.json").stat().st_mtime_ns == stamp
    scene = load_scene(path)
    assert all(scene.files[i].depth_prior is not None for i in scene.train)
    assert all(scene.files[i].depth_prior is None for i in scene.test)


def test_masks_and_feature_maps(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    from data_fixtures import copy_of
    from PIL import Image

    root = copy_of("lightfield", tmp_path / "lf")
    (root / "masks").mkdir()
    mask = np.zeros((96, 128), np.uint8)
    mask[:, 64:] = 255
    Image.fromarray(mask).save(root / "masks" / "r0_c0.png")
    (root / "features").mkdir()
    feats = np.random.default_rng(0).normal(size=(24, 32, 8)).astype(np.float16)
    np.save(root / "features" / "r0_c0.npy", feats)
    scene = load_scene(root)
    assert "mask 1/13" in scene.summary() and "features 1/13" in scene.summary()
    v = scene.view(scene.index("r0_c0.png"))
    assert v.mask.shape == (96, 128, 1) and v.mask[:, :64].sum() == 0 and v.mask[:, 64:].all()
    np.testing.assert_allclose(v.features.numpy(), feats.astype(np.float32))
    other = scene.view(scene.index("r0_c1.png"))
    assert other.mask is None and other.features is None
    small = scene.downscaled(2).view(scene.index("r0_c0.png"))
    assert small.mask.shape == (48, 64, 1) and small.mask[:, 32:].all() and not small.mask[:, :32].any()


def test_views_rendered_in_parallel_equal_one_at_a_time():
    from warpgs.data.formats import raytrace
    from warpgs.data.formats.synthetic import RigSettings, orbit_rig, render_views, scene_definition

    cameras = orbit_rig(RigSettings(width=40, height=30, n_orbit=4))[0]
    definition = scene_definition()
    serial = [raytrace.render(definition, cam) for cam in cameras]
    threaded = render_views(definition, cameras, max_workers=4)
    assert len(threaded) == len(cameras)
    for a, b in zip(serial, threaded):
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.labels, b.labels)
