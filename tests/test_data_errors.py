"""Bad inputs raise clear errors that name the file at fault."""
import json
import re

import numpy as np
import pytest
from PIL import Image

from data_fixtures import copy_of, write_rgb
from warpgs.data import MissingSceneFile, SceneError, load_colmap, load_scene, load_transforms, save_colmap
from warpgs.data.depth.files import write_exr


@pytest.fixture
def lf(tmp_path):
    return copy_of("lightfield", tmp_path / "lf")


def _names(exc_info, path):
    assert str(path) in str(exc_info.value), str(exc_info.value)


def test_missing_image(lf):
    (lf / "images" / "r1_c2.png").unlink()
    with pytest.raises(MissingSceneFile) as exc:
        load_scene(lf)
    _names(exc, lf / "images" / "r1_c2.png")
    assert isinstance(exc.value, FileNotFoundError)


def test_missing_image_in_a_colmap_scene(tmp_path):
    root = copy_of("orbit", tmp_path / "orbit")
    (root / "images" / "orbit_007.png").unlink()
    with pytest.raises(MissingSceneFile) as exc:
        load_scene(root)
    _names(exc, root / "images" / "orbit_007.png")


def test_truncated_image(lf):
    path = lf / "images" / "r1_c1.png"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    scene = load_scene(lf)  # the header is intact, so loading (header checks) passes...
    with pytest.raises(SceneError, match="truncated") as exc:
        scene.image(scene.index("r1_c1.png"))  # ...and decoding names the file
    _names(exc, path)
    with pytest.raises(SceneError) as exc:
        scene.validate(decode=True)
    _names(exc, path)


def test_truncated_jpeg_and_non_image(tmp_path):
    from warpgs.data.formats.image_io import read_image

    path = tmp_path / "a.jpg"
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(path)
    path.write_bytes(path.read_bytes()[:300])
    with pytest.raises(SceneError) as exc:
        read_image(path)
    _names(exc, path)
    junk = tmp_path / "b.png"
    junk.write_text("this is not a picture")
    with pytest.raises(SceneError, match="not a readable image") as exc:
        read_image(junk)
    _names(exc, junk)


def test_wrong_image_size(lf):
    path = lf / "images" / "r0_c2.png"
    write_rgb(path, 64, 48)
    with pytest.raises(SceneError, match=re.escape("64x48")) as exc:
        load_scene(lf)
    _names(exc, path)
    assert "128x96" in str(exc.value)


def test_empty_and_missing_folders(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SceneError, match="no scene found") as exc:
        load_scene(tmp_path / "empty")
    _names(exc, tmp_path / "empty")
    with pytest.raises(MissingSceneFile) as exc:
        load_scene(tmp_path / "nowhere")
    _names(exc, tmp_path / "nowhere")
    (tmp_path / "imgs" / "images").mkdir(parents=True)
    write_rgb(tmp_path / "imgs" / "images" / "only.png", 32, 32)
    with pytest.raises(SceneError, match="at least 2 images") as exc:
        load_scene(tmp_path / "imgs")
    _names(exc, tmp_path / "imgs" / "images")


def test_nan_in_depth_maps(lf):
    path = lf / "depth" / "r0_c1.exr"
    depth = np.full((96, 128), 3.0, np.float32)
    depth[5, 7] = np.nan
    import OpenEXR  # write the broken file directly: our writer refuses NaN

    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                  "warpgs_kind": "depth"}, {"Z": depth}).write(str(path))
    scene = load_scene(lf)
    with pytest.raises(SceneError, match="NaN") as exc:
        scene.view(scene.index("r0_c1.png"))
    _names(exc, path)
    # The same for a .npy depth prior.
    (lf / "depth_priors").mkdir()
    prior = np.full((96, 128), 0.3, np.float32)
    prior[0, 0] = np.nan
    np.save(lf / "depth_priors" / "r2_c2.npy", prior)
    (lf / "depth_priors" / "format.json").write_text('{"kind": "inverse_depth"}')
    scene = load_scene(lf)
    with pytest.raises(SceneError, match="1 NaN") as exc:
        scene.inv_depth_prior_np(scene.index("r2_c2.png"))
    _names(exc, lf / "depth_priors" / "r2_c2.npy")


def test_truncated_and_mis_sized_depth(lf):
    path = lf / "depth" / "r1_c0.exr"
    path.write_bytes(path.read_bytes()[:500])
    scene = load_scene(lf)
    with pytest.raises(SceneError, match="EXR") as exc:
        scene.depth_np(scene.index("r1_c0.png"))
    _names(exc, path)
    write_exr(lf / "depth" / "r1_c1.exr", np.ones((50, 50), np.float32), "depth")
    with pytest.raises(SceneError, match="50x50") as exc:
        scene.depth_np(scene.index("r1_c1.png"))
    _names(exc, lf / "depth" / "r1_c1.exr")


def test_broken_colmap_models(tmp_path):
    root = copy_of("orbit", tmp_path / "orbit")
    model = root / "sparse" / "0"
    (model / "points3D.txt").unlink()
    with pytest.raises(MissingSceneFile) as exc:
        load_colmap(root)
    _names(exc, model / "points3D.txt")
    # A binary model with a truncated images.bin.
    scene = load_colmap(copy_of("orbit", tmp_path / "orbit2"))
    binary = tmp_path / "bin"
    save_colmap(scene.cameras, binary / "sparse" / "0", scene.points, binary=True)
    (binary / "images").symlink_to(tmp_path / "orbit2" / "images")
    images_bin = binary / "sparse" / "0" / "images.bin"
    images_bin.write_bytes(images_bin.read_bytes()[:1000])
    with pytest.raises(SceneError) as exc:
        load_colmap(binary)
    _names(exc, images_bin)


def test_inconsistent_split_and_labels(lf):
    (lf / "lightfield.json").unlink()  # make it a plain COLMAP scene that reads split.json
    (lf / "split.json").write_text(json.dumps({"train": ["r0_c0.png", "nope.png"], "test": []}))
    with pytest.raises(SceneError, match="nope.png") as exc:
        load_scene(lf)
    _names(exc, lf / "split.json")
    (lf / "split.json").unlink()
    labels = np.array(Image.open(lf / "labels" / "r0_c0.png"))
    labels[0, 0] = 42
    Image.fromarray(labels).save(lf / "labels" / "r0_c0.png")
    scene = load_scene(lf)
    with pytest.raises(SceneError, match="42") as exc:
        scene.labels_np(scene.index("r0_c0.png"))
    _names(exc, lf / "labels" / "r0_c0.png")


def test_broken_transforms(tmp_path):
    write_rgb(tmp_path / "images" / "a.png", 20, 10)
    frame = {"file_path": "images/b.png", "transform_matrix": np.eye(4).tolist()}
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 10.0, "frames": [frame]}))
    with pytest.raises(MissingSceneFile) as exc:
        load_transforms(tmp_path)
    _names(exc, tmp_path / "images" / "b.png")
    (tmp_path / "transforms.json").write_text('{"frames": [')
    with pytest.raises(SceneError, match="JSON") as exc:
        load_transforms(tmp_path)
    _names(exc, tmp_path / "transforms.json")
    frame["file_path"] = "images/a.png"
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": [frame]}))
    with pytest.raises(SceneError, match="focal length") as exc:
        load_transforms(tmp_path)
    _names(exc, tmp_path / "transforms.json")


def test_a_video_given_as_a_scene_path_says_how_to_use_it(tmp_path):
    video = tmp_path / "clip.mp4"
    video.write_bytes(b"not decoded: the suffix decides")
    with pytest.raises(SceneError, match=r"clip\.mp4: a video, not a scene folder: .*--data .*warpgs-process"):
        load_scene(video)
    with pytest.raises(SceneError, match="a scene is a folder, not a file"):
        load_scene(tmp_path / "clip.txt" if (tmp_path / "clip.txt").write_text("x") else None)
