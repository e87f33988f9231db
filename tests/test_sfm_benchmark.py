"""benchmarks/sfm.py --reference: registered cameras are compared with known poses of the same images."""
import sys
from pathlib import Path

import numpy as np
import pytest

from pose_helpers import K, in_other_frame, with_pose
from warpgs.data.camera import Camera, look_at

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import sfm  # noqa: E402


def ring(n=8, radius=4.0, name="v{}.png"):
    return [Camera(K, look_at((radius * np.cos(a), radius * np.sin(a), 1.0), (0, 0, 0)), 80, 60, name=name.format(i))
            for i, a in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False))]


def similar(cams):
    """The same cameras in another frame (SfM's gauge): centres scaled and shifted, orientations unchanged."""
    return in_other_frame(cams, np.eye(3), s=0.4, t=(1.0, -2.0, 0.5))


def test_a_similarity_transform_of_the_reference_agrees_and_a_wrong_pose_is_found():
    reference = ring()
    found = sfm.pose_agreement(similar(reference), reference)
    assert found["compared"] == 8 and found["rotation_deg_max"] < 1e-6 and found["center_max"] < 1e-6
    wrong = similar(reference)
    down = np.array(look_at((0, 0, 9), (0, 0, 0), up=(0, 1, 0)))[:3, :3]
    wrong[3] = with_pose(wrong[3], down, wrong[3].center)  # one camera turned to look down, from where it stood
    found = sfm.pose_agreement(wrong, reference)
    assert found["over_5deg"] == 1 and found["rotation_deg_max"] > 30 and found["rotation_deg_median"] < 1e-6


def test_only_images_of_both_sets_are_compared_and_too_few_is_an_error():
    reference = ring()
    found = sfm.pose_agreement(similar(reference)[:5] + ring(3, name="other{}.png"), reference)
    assert found["compared"] == 5
    with pytest.raises(SystemExit, match="--reference"):
        sfm.pose_agreement(ring(4, name="x{}.png"), reference)
