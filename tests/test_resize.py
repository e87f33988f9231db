"""Per-pixel map resizing (warpgs/data/formats/resize.py): the numpy and torch paths sample the same pixels."""
import numpy as np
import pytest
import torch

from warpgs.data.formats.resize import resize_area, resize_nearest, resize_tensor


@pytest.mark.parametrize("size, out", [((37, 53), (13, 19)), ((8, 8), (3, 5)), ((5, 7), (10, 14)), ((1, 9), (1, 4))])
def test_nearest_takes_the_same_source_pixels_from_numpy_and_torch(size, out):
    ids = np.arange(size[0] * size[1], dtype=np.int64).reshape(size)  # every pixel its own id
    a = resize_nearest(ids, out[1], out[0])
    b = resize_tensor(torch.from_numpy(ids), out[1], out[0], "nearest").numpy()
    np.testing.assert_array_equal(a, b)
    # each output pixel's id is the source pixel under its centre
    rows, cols = np.divmod(a, size[1])
    centres_y = (np.arange(out[0]) + 0.5) * size[0] / out[0]
    centres_x = (np.arange(out[1]) + 0.5) * size[1] / out[1]
    assert (np.abs(rows + 0.5 - centres_y[:, None]) <= 0.5).all()
    assert (np.abs(cols + 0.5 - centres_x[None, :]) <= 0.5).all()


def test_area_averages_each_footprint():
    img = np.arange(16, dtype=np.float32).reshape(4, 4)
    np.testing.assert_allclose(resize_area(img, 2, 2), [[2.5, 4.5], [10.5, 12.5]])
