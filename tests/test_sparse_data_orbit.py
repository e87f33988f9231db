"""benchmarks/sparse_data_orbit.py: a walk-around capture's photos renamed so that name order is capture order,
area-averaged to 1/factor, and bad input named."""
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

from sparse_data_orbit import numbered_name, orbit_images  # noqa: E402


def _photo(path: Path, value: int, size=(8, 6)):
    Image.fromarray(np.full((size[1], size[0], 3), value, np.uint8)).save(path, quality=100)


def test_names_sort_in_capture_order_and_images_are_scaled(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for n in (1, 2, 10):  # as files: 1, 10, 2 in name order
        _photo(src / f"{n}.jpg", 20 * n)
    out = orbit_images(src, tmp_path / "out", factor=2)
    assert [p.name for p in out] == ["0001.jpg", "0002.jpg", "0010.jpg"]
    img = np.asarray(Image.open(out[2]))
    assert img.shape == (3, 4, 3) and abs(int(img.mean()) - 200) <= 2  # the 10th photo, at half size
    assert numbered_name(Path("IMG_4831_25.JPG")) == "0025.jpg" and numbered_name(Path("frame_0082.png")) == "0082.jpg"


def test_bad_input_names_the_file(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    _photo(src / "cover.jpg", 10)
    with pytest.raises(SystemExit, match="cover.jpg: no number"):
        orbit_images(src, tmp_path / "out")
    (src / "cover.jpg").unlink()
    _photo(src / "a_7.jpg", 10)
    _photo(src / "b_007.jpg", 10)
    with pytest.raises(SystemExit, match="two images numbered 0007.jpg"):
        orbit_images(src, tmp_path / "out")
    with pytest.raises(SystemExit, match="--factor"):
        orbit_images(src, tmp_path / "out", factor=0)
