"""benchmarks/sfm.py --reference: registered cameras are compared with known poses of the same images."""
import sys
from pathlib import Path

import numpy as np
import pytest

from warpgs.data.camera import Camera, look_at

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import sfm  # noqa: E402

K = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])


def ring(n=8, radius=4.0, name="v{}.png"):
    return [Camera(K, look_at((radius * np.cos(a), radius * np.sin(a), 1.0), (0, 0, 0)), 80, 60, name=name.format(i))
            for i, a in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False))]


def similar(cams, scale=2.5, shift=(1.0, -2.0, 0.5)):
    """The same cameras in another frame (SfM's gauge): centres scaled and shifted, orientations unchanged."""
    out = []
    for c in cams:
        V = np.array(c.viewmat, dtype=np.float64)
        centre = scale * c.center + np.asarray(shift)
        V[:3, 3] = -V[:3, :3] @ centre
        out.append(Camera(K, V, 80, 60, name=c.name))
    return out


def test_a_similarity_transform_of_the_reference_agrees_and_a_wrong_pose_is_found():
    reference = ring()
    found = sfm.pose_agreement(similar(reference), reference)
    assert found["compared"] == 8 and found["rotation_deg_max"] < 1e-6 and found["center_max"] < 1e-6
    wrong = similar(reference)
    V = np.array(wrong[3].viewmat, dtype=np.float64)
    centre = wrong[3].center
    V[:3, :3] = np.array(look_at((0, 0, 9), (0, 0, 0), up=(0, 1, 0)))[:3, :3]  # one camera turned to look down,
    V[:3, 3] = -V[:3, :3] @ centre  # from where it stood
    wrong[3] = Camera(K, V, 80, 60, name=wrong[3].name)
    found = sfm.pose_agreement(wrong, reference)
    assert found["over_5deg"] == 1 and found["rotation_deg_max"] > 30 and found["rotation_deg_median"] < 1e-6


def test_only_images_of_both_sets_are_compared_and_too_few_is_an_error():
    reference = ring()
    found = sfm.pose_agreement(similar(reference)[:5] + ring(3, name="other{}.png"), reference)
    assert found["compared"] == 5
    with pytest.raises(SystemExit, match="--reference"):
        sfm.pose_agreement(ring(4, name="x{}.png"), reference)
