"""Light-field folders, their grid poses and the sparse-view split protocols; scene-type detection."""
import json

import numpy as np
import pytest

from data_fixtures import synthetic_dir, write_rgb
from warpgs.data import SceneError, detect_format, grid_protocol_split, llff_split, load_lightfield, load_scene


def test_llff_protocol():
    train, test = llff_split(20, n_train=3)
    assert test == [0, 8, 16]
    assert train == [1, 10, 19]  # spread evenly over the 17 remaining views, ends included
    train, test = llff_split(10)
    assert test == [0, 8] and train == [1, 2, 3, 4, 5, 6, 7, 9]
    with pytest.raises(ValueError):
        llff_split(10, n_train=9)


def test_grid_protocol_on_a_larger_array():
    positions = {f"r{r}_c{c}.png": (float(r), float(c)) for r in range(5) for c in range(5)}
    positions["between.png"] = (1.5, 2.5)
    names = sorted(positions)
    train, test = grid_protocol_split(positions, names, k=3)
    assert sorted(positions[names[i]] for i in train) == [(r, c) for r in (0.0, 2.0, 4.0) for c in (0.0, 2.0, 4.0)]
    assert len(test) == 17 and "between.png" in [names[i] for i in test]
    with pytest.raises(ValueError):
        grid_protocol_split(positions, names, k=7)


def _planar_folder(root, rows=3, cols=3, name="r{r}_c{c}.png", views=None):
    for r in range(rows):
        for c in range(cols):
            write_rgb(root / "images" / name.format(r=r, c=c), 40, 30, seed=r * cols + c)
    spec = {"baseline": [0.1, 0.2], "intrinsics": {"fx": 50.0, "fy": 50.0, "cx": 20.0, "cy": 15.0}}
    if views is not None:
        spec["views"] = views
    (root / "lightfield.json").write_text(json.dumps(spec))
    return root


def test_planar_grid_poses_from_baseline(tmp_path):
    root = _planar_folder(tmp_path / "lf")
    scene = load_scene(root)
    assert scene.source == "lightfield" and len(scene.train) == 9 and scene.test == []
    for name in scene.names:
        r, c = scene.metadata["grid_positions"][name]
        cam = scene.cameras[scene.index(name)]
        np.testing.assert_allclose(cam.center, [0.1 * c, 0.2 * r, 0.0], atol=1e-12)
        np.testing.assert_allclose(cam.viewmat[:3, :3], np.eye(3))
        assert cam.fx == 50.0 and (cam.width, cam.height) == (40, 30)


def _project(cam, point):
    p = cam.K @ (cam.viewmat[:3, :3] @ point + cam.viewmat[:3, 3])
    return p[:2] / p[2]


def test_rectified_array_from_measured_centres(tmp_path):
    """A rectified array (Stanford's archive): measured centres, and principal points shifted so that the
    reference plane projects alike in every view, while a nearer point moves against the camera."""
    root = _planar_folder(tmp_path / "lf")
    spec = json.loads((root / "lightfield.json").read_text())
    del spec["baseline"]
    centres = {f"r{r}_c{c}.png": [0.1 * c + 0.01 * r, 0.2 * r - 0.005 * c] for r in range(3) for c in range(3)}
    spec.update(centres=centres, reference_depth=2.0)
    (root / "lightfield.json").write_text(json.dumps(spec))
    scene = load_scene(root)
    on_plane, near = np.array([0.3, -0.1, 2.0]), np.array([0.3, -0.1, 1.0])
    ref = scene.cameras[scene.index("r0_c0.png")]
    for name, (x, y) in centres.items():
        cam = scene.cameras[scene.index(name)]
        np.testing.assert_allclose(cam.center, [x, y, 0.0], atol=1e-12)
        np.testing.assert_allclose(_project(cam, on_plane), _project(ref, on_plane), atol=1e-9)
        # fx * centre * (1/z0 - 1/z): the near point moves left as the camera moves right
        shift = _project(cam, near) - _project(ref, near)
        np.testing.assert_allclose(shift, 50.0 * (np.array([x, y]) - centres["r0_c0.png"]) * (1 / 2.0 - 1 / 1.0),
                                   atol=1e-9)
    # Downscaling keeps the plane's agreement (the shifted principal points scale with the image).
    half = load_scene(root, downscale=2)
    np.testing.assert_allclose(_project(half.cameras[0], on_plane), _project(half.cameras[5], on_plane), atol=1e-9)
    spec["centres"].pop("r2_c2.png")
    (root / "lightfield.json").write_text(json.dumps(spec))
    with pytest.raises(SceneError, match="no centre for r2_c2.png"):
        load_scene(root)
    spec["centres"]["r2_c2.png"] = [0.2, 0.4]
    spec["reference_depth"] = -1
    (root / "lightfield.json").write_text(json.dumps(spec))
    with pytest.raises(SceneError, match="reference_depth"):
        load_scene(root)


def test_grid_positions_from_file_names_and_explicit_views(tmp_path):
    root = _planar_folder(tmp_path / "numbered", name="{r:02d}_{c:02d}.png")
    scene = load_lightfield(root)
    assert scene.metadata["grid_positions"]["02_01.png"] == (2.0, 1.0)
    views = {"a.png": [0, 0], "b.png": [0, 1], "c.png": [1, 0], "d.png": [1, 1]}
    root = tmp_path / "explicit"
    for n in views:
        write_rgb(root / "images" / n, 40, 30)
    (root / "lightfield.json").write_text(json.dumps({"views": views, "baseline": [0.1, 0.1],
                                                      "intrinsics": {"fx": 50, "fy": 50, "cx": 20, "cy": 15}}))
    scene = load_lightfield(root, k=2)
    assert len(scene.train) == 4
    with pytest.raises(SceneError, match="3x3 training grid"):
        load_lightfield(root, k=3)


def test_lightfield_without_poses(tmp_path):
    root = tmp_path / "lf"
    for r in range(3):
        for c in range(3):
            write_rgb(root / "images" / f"r{r}_c{c}.png", 40, 30)
    with pytest.raises(SceneError, match="no poses") as exc:
        load_lightfield(root, run_sfm_if_needed=False)
    assert str(root) in str(exc.value)


def test_split_options_on_the_synthetic_light_field():
    root = synthetic_dir("lightfield")
    assert detect_format(root) == "lightfield"
    assert len(load_scene(root, split="all").train) == 13
    by_file = load_scene(root, split="file")  # split.json written by the generator says the same as the grid
    grid = load_scene(root)
    assert by_file.train == grid.train and by_file.test == grid.test


def test_detect_format(tmp_path):
    assert detect_format(synthetic_dir("orbit")) == "colmap"
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "transforms.json").write_text('{"frames": []}')
    assert detect_format(tmp_path / "t") == "transforms"
    write_rgb(tmp_path / "i" / "images" / "x.png", 8, 8)
    assert detect_format(tmp_path / "i") == "images"
