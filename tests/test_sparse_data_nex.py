"""benchmarks/sparse_data_nex.py: an LLFF scene in NeX's layout ([N, 14] poses, intrinsics in hwf_cxcy.npy, the
principal point off the centre) becomes a standard LLFF folder whose cameras project points where the original
pinhole cameras did, to within the half pixel the crop leaves; bad input names the file."""
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from sparse_data_nex import centred_window, convert  # noqa: E402
from warpgs.data import load_scene  # noqa: E402
from warpgs.data.formats.image_io import write_png  # noqa: E402


def test_the_window_is_centred_on_the_principal_point_within_half_a_pixel():
    for size, centre in ((996, 490.9), (746, 363.1), (1004, 502.1), (753, 381.1), (100, 50.0), (101, 80.2)):
        a, b = centred_window(size, centre)
        assert 0 <= a < b <= size and (b - a) % 2 == 0
        assert abs((a + b) / 2 - centre) <= 0.5
        assert b - a >= 2 * int(np.floor(min(centre, size - centre))) - 1


def _nex_scene(root: Path, n=4, h=60, w=80, f=70.0, cx=37.3, cy=33.6):
    rng = np.random.default_rng(0)
    (root / "images").mkdir(parents=True)
    poses = []
    for i in range(n):
        c2w = np.eye(4)
        c2w[:3, 3] = [0.2 * i, 0.0, 0.0]
        # LLFF's axes: columns (down, right, back) of a camera looking down -z with x to the right, y up
        down, right, back = -c2w[:3, 1], c2w[:3, 0], c2w[:3, 2]
        poses.append(np.concatenate([np.stack([down, right, back, c2w[:3, 3]], 1).ravel(), [1.0, 10.0]]))
        write_png(root / "images" / f"img{i + 1:03d}.png", rng.uniform(0, 1, (h, w, 3)).astype(np.float32))
    np.save(root / "poses_bounds.npy", np.array(poses))
    np.save(root / "hwf_cxcy.npy", np.array([h, w, f, f, cx, cy]))
    return h, w, f, cx, cy


def test_converted_cameras_project_as_the_original_pinhole(tmp_path):
    h, w, f, cx, cy = _nex_scene(tmp_path / "nex")
    out = convert(tmp_path / "nex", tmp_path / "llff")
    pb = np.load(out / "poses_bounds.npy")
    assert pb.shape == (4, 17)
    scene = load_scene(out, split="all")
    cam = scene.cameras[0]
    (r0, _), (c0, _) = centred_window(h, cy), centred_window(w, cx)
    assert (cam.height, cam.width) == (int(pb[0, 4]), int(pb[0, 9]))
    # a world point in front of camera 0 (at the origin, x right, y up, looking down -z): the original pinhole's
    # pixel less the crop's offset, against the loaded camera's own projection (OpenCV axes: x right, y down, +z)
    x, y, z = 0.3, -0.2, -4.0
    u_orig, v_orig = cx + f * x / -z, cy - f * y / -z
    p = cam.viewmat @ np.array([x, y, z, 1.0])
    uvw = cam.K @ p[:3]
    u_new, v_new = uvw[0] / uvw[2], uvw[1] / uvw[2]
    assert p[2] > 0 and abs((u_orig - c0) - u_new) <= 0.5 and abs((v_orig - r0) - v_new) <= 0.5


def test_bad_input_names_the_file(tmp_path):
    _nex_scene(tmp_path / "nex")
    np.save(tmp_path / "nex" / "poses_bounds.npy", np.zeros((4, 17)))
    with pytest.raises(SystemExit, match=r"poses_bounds\.npy: expected an \[N, 14\] array"):
        convert(tmp_path / "nex", tmp_path / "out")
    (tmp_path / "nex" / "hwf_cxcy.npy").unlink()
    with pytest.raises(SystemExit, match="hwf_cxcy.npy: missing"):
        convert(tmp_path / "nex", tmp_path / "out")
