"""pycolmap SfM on the synthetic scene's dense orbit recovers the true poses up to a similarity."""
import shutil
import time

import numpy as np
import pytest

from data_fixtures import synthetic_dir
from warpgs.data import load_colmap, load_scene, run_sfm
from warpgs.data.sfm.sim3 import pose_errors, umeyama

# Tolerances at 128x96: (max rotation deg, mean rotation deg, max centre error as a fraction of the orbit radius).
# Runs are single-threaded, hence reproducible (multi-threaded pycolmap varies from run to run, and at this size
# once broke a view by 30 deg). Measured: exhaustive 1.34 deg max, 0.48 mean, 2.5%; the error is set by SIFT
# localisation on such small images (a 256x192 render roughly halved it in an earlier trial). Sequential matching
# never pairs the last views with the first, so the ring's drift is not closed: 1.85 deg max, 1.18 mean, 3.4%.
TOLERANCES = {"exhaustive": (2.5, 1.0, 0.05), "sequential": (3.5, 2.0, 0.07)}


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    dst = 2.5 * src @ R.T + [1.0, -2.0, 0.5]
    s, R_est, t = umeyama(src, dst)
    assert abs(s - 2.5) < 1e-9 and np.allclose(R_est, R) and np.allclose(t, [1.0, -2.0, 0.5])


@pytest.mark.parametrize("matcher", ["exhaustive", "sequential"])
def test_sfm_recovers_the_orbit_poses(tmp_path, matcher):
    truth = load_scene(synthetic_dir("orbit"), split="all")
    shutil.copytree(synthetic_dir("orbit") / "images", tmp_path / "images")
    K = truth.cameras[0].K
    start = time.perf_counter()
    model = run_sfm(tmp_path / "images", tmp_path, matcher=matcher, camera_model="PINHOLE",
                    camera_params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], refine_intrinsics=False, num_threads=1)
    seconds = time.perf_counter() - start
    assert model == tmp_path / "sparse" / "0"
    est = load_colmap(tmp_path, split="all")
    assert len(est) == len(truth) == 36  # every view registered
    assert est.points is not None and len(est.points) > 300
    errors = pose_errors([est.cameras[est.index(n)] for n in truth.names], truth.cameras)
    radius = np.linalg.norm(truth.cameras[0].center - [0.0, 0.0, 0.35])
    mean_rot = float(np.mean(errors["rotation_deg"]))
    print(f"SfM ({matcher}) on 36 orbit views at 128x96: {seconds:.1f} s; rotation error max "
          f"{errors['max_rotation_deg']:.2f} deg, mean {mean_rot:.2f} deg; centre error max "
          f"{errors['max_center'] / radius:.2%} of the orbit radius")
    max_rot, max_mean_rot, max_centre = TOLERANCES[matcher]
    assert errors["max_rotation_deg"] < max_rot and mean_rot < max_mean_rot
    assert errors["max_center"] < max_centre * radius
