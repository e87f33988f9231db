"""warpgs.data.depth.fill: the invalid pixels of a prior are filled from the valid ones, edge-aware, and
compute_depth_priors(fill_confidence=...) writes them with that confidence."""
import numpy as np
import pytest

from test_sparse_llff_prior import Z0, _plane_coords, plane_scene_with_points
from warpgs.data import PlaneSweepStereo, compute_depth_priors
from warpgs.data.depth.files import read_exr_channels
from warpgs.data.depth.fill import fill_inverse_depth

ROWS, COLS = 120, 160


def _grid():
    return np.mgrid[0:ROWS, 0:COLS].astype(np.float64)


def test_a_hole_in_a_plane_is_filled_with_the_plane():
    # The inverse depth of a plane is affine in the pixel coordinates: the harmonic fill reproduces it.
    v, u = _grid()
    plane = 0.4 + 0.002 * u + 0.001 * v
    valid = np.ones((ROWS, COLS), bool)
    valid[30:100, 40:140] = False
    filled, mask = fill_inverse_depth(plane, valid, np.full((ROWS, COLS, 3), 0.5))
    assert np.array_equal(mask, ~valid)
    assert np.array_equal(filled[valid], plane[valid])  # valid pixels never change
    rel = np.abs(filled - plane)[~valid] / plane[~valid]
    assert rel.mean() < 0.005 and rel.max() < 0.02, (rel.mean(), rel.max())


def test_the_fill_follows_image_edges():
    # Two surfaces meet at an image edge; a hole straddles it. Each side should be filled from its own surface.
    v, u = _grid()
    left = u < COLS // 2
    inv = np.where(left, 1.0, 0.5)
    valid = np.ones((ROWS, COLS), bool)
    valid[20:100, 30:130] = False
    edges = np.where(left[..., None], 0.2, 0.8) * np.ones(3)
    flat = np.full((ROWS, COLS, 3), 0.5)
    err_edges = np.abs(fill_inverse_depth(inv, valid, edges)[0] - inv)[~valid].mean()
    err_flat = np.abs(fill_inverse_depth(inv, valid, flat)[0] - inv)[~valid].mean()
    assert err_edges < 0.3 * err_flat, (err_edges, err_flat)


def test_nothing_to_fill_from_or_nothing_to_fill_and_bad_shapes():
    inv = np.ones((ROWS, COLS))
    img = np.zeros((ROWS, COLS, 3))
    for valid in (np.zeros((ROWS, COLS), bool), np.ones((ROWS, COLS), bool)):
        out, mask = fill_inverse_depth(inv, valid, img)
        assert not mask.any() and np.array_equal(out, inv)
    with pytest.raises(ValueError, match="image"):
        fill_inverse_depth(inv, np.ones((ROWS, COLS), bool), np.zeros((ROWS, COLS + 1, 3)))
    with pytest.raises(ValueError, match="sigma_color"):
        fill_inverse_depth(inv, np.ones((ROWS, COLS), bool), img, sigma_color=0.0)


def test_priors_written_with_a_fill_cover_the_textureless_square(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "cache"))
    scene = plane_scene_with_points(tmp_path / "scene")
    X, Y = _plane_coords(0.0)
    estimator = PlaneSweepStereo(near=3.0, far=8.0)
    _, plain = compute_depth_priors(scene, estimator, views=[1], out_dir=tmp_path / "plain")
    _, filled = compute_depth_priors(scene, estimator, views=[1], out_dir=tmp_path / "filled", fill_confidence=0.3)
    before, after = plain["views"]["IMG_001.png"], filled["views"]["IMG_001.png"]
    assert before["valid_fraction"] < 1.0 and after["valid_fraction"] == pytest.approx(1.0)
    assert after["filled_fraction"] == pytest.approx(1.0 - before["valid_fraction"])
    a = read_exr_channels(tmp_path / "plain" / "IMG_001.exr")
    b = read_exr_channels(tmp_path / "filled" / "IMG_001.exr")
    was_valid = a["valid"] > 0
    new = ~was_valid
    square = (np.abs(X) < 0.5) & (np.abs(Y) < 0.5)
    assert new[square].mean() > 0.2  # the stereo leaves much of the flat square out
    np.testing.assert_allclose(b["Z"][was_valid], a["Z"][was_valid])  # estimated pixels keep value and confidence
    np.testing.assert_allclose(b["confidence"][was_valid], a["confidence"][was_valid])
    assert np.allclose(b["confidence"][new], 0.3)
    # The flat square is a piece of the plane: the filled inverse depth is the plane's, 1 / Z0.
    assert np.abs(b["Z"][new & square] * Z0 - 1.0).max() < 0.02
    with pytest.raises(ValueError, match="fill_confidence"):
        compute_depth_priors(scene, estimator, views=[1], out_dir=tmp_path / "bad", fill_confidence=1.5)
