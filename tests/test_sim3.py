"""warpgs.data.sfm.sim3: aligning a reconstruction to known poses, also when the camera centres lie on a line."""
import numpy as np
import pytest

from pose_helpers import K, in_other_frame, turned
from warpgs.data.camera import Camera, look_at
from warpgs.data.sfm.sim3 import orientation_alignment, pose_errors


def rotation(axis, degrees):
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    a = np.radians(degrees)
    X = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * X + (1 - np.cos(a)) * X @ X


def sweep(n=10):
    """A video sweep: centres on a straight line, each camera turned a little differently."""
    return [Camera(K, look_at((0.5 * i, -5.0, 1.0), (0.4 * i + np.sin(i), 0.0, 0.3 * np.cos(i))), 80, 60,
                   name=f"f{i}.png") for i in range(n)]


def test_orientations_align_a_sweep_exactly_where_its_centres_cannot_fix_the_roll():
    reference = sweep()
    Q = rotation((0.3, -1.0, 0.5), 70.0)
    estimated = in_other_frame(reference, Q)
    assert np.abs(orientation_alignment(estimated, reference) - Q).max() < 1e-9
    found = pose_errors(estimated, reference, align="orientations")
    assert max(found["rotation_deg"]) < 1e-4 and max(found["center"]) < 1e-9 and found["scale"] == pytest.approx(0.3)
    # Centres on a line leave the rotation about that line free: the centre fit gets the orientations wrong.
    assert max(pose_errors(estimated, reference, align="centres")["rotation_deg"]) > 1.0


def test_a_few_wrong_poses_do_not_move_the_orientation_fit():
    reference = sweep(12)
    Q = rotation((1.0, 0.2, 0.0), -40.0)
    estimated = in_other_frame(reference, Q)
    for k in (2, 7):  # two cameras turned half around, as SfM does when it puts a view on the wrong side
        estimated[k] = turned(estimated[k], rotation((0, 1, 0), 180.0))
    assert np.degrees(np.arccos((np.trace(orientation_alignment(estimated, reference) @ Q.T) - 1) / 2)) < 1e-4
    errors = pose_errors(estimated, reference, align="orientations")["rotation_deg"]
    assert sum(e > 5 for e in errors) == 2 and sorted(errors)[9] < 1e-4


def test_unknown_alignment_is_refused():
    with pytest.raises(ValueError, match="align"):
        pose_errors(sweep(), sweep(), align="points")
