"""pycolmap SfM on the synthetic scene's dense orbit recovers the true poses up to a similarity; which pairs get
matched (exhaustive, sequential, visual-word retrieval, pose neighbours)."""
import shutil
import time

import numpy as np
import pytest

from data_fixtures import synthetic_dir
from warpgs.data import load_colmap, load_scene, run_sfm
from warpgs.data.sfm import pairs
from warpgs.data.sfm.sim3 import pose_errors, umeyama

# Tolerances at 128x96: (max rotation deg, mean rotation deg, max centre error as a fraction of the orbit radius).
# Runs are single-threaded, hence reproducible (multi-threaded pycolmap varies from run to run, and at this size
# once broke a view by 30 deg). Measured: exhaustive 1.34 deg max, 0.48 mean, 2.5%; the error is set by SIFT
# localisation on such small images (a 256x192 render roughly halved it in an earlier trial). Sequential matching
# never pairs the last views with the first, so the ring's drift is not closed: 1.85 deg max, 1.18 mean, 3.4%.
# Retrieval (each view with its 20 most similar by visual words + the name-order window) closes the ring too.
TOLERANCES = {"exhaustive": (2.5, 1.0, 0.05), "sequential": (3.5, 2.0, 0.07), "retrieval": (2.5, 1.0, 0.05)}


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    dst = 2.5 * src @ R.T + [1.0, -2.0, 0.5]
    s, R_est, t = umeyama(src, dst)
    assert abs(s - 2.5) < 1e-9 and np.allclose(R_est, R) and np.allclose(t, [1.0, -2.0, 0.5])


@pytest.mark.parametrize("matcher,mapper", [("exhaustive", "incremental"), ("sequential", "incremental"),
                                            ("retrieval", "incremental"), ("exhaustive", "global")])
def test_sfm_recovers_the_orbit_poses(tmp_path, matcher, mapper, monkeypatch, capsys):
    truth = load_scene(synthetic_dir("orbit"), split="all")
    shutil.copytree(synthetic_dir("orbit") / "images", tmp_path / "images")
    K = truth.cameras[0].K
    if matcher == "retrieval":  # what "auto" picks for sets larger than EXHAUSTIVE_MAX_IMAGES
        monkeypatch.setattr(pairs, "EXHAUSTIVE_MAX_IMAGES", 20)
    start = time.perf_counter()
    model = run_sfm(tmp_path / "images", tmp_path, matcher="auto" if matcher == "retrieval" else matcher,
                    camera_model="PINHOLE", camera_params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
                    refine_intrinsics=False, num_threads=1, mapper=mapper)
    seconds = time.perf_counter() - start
    err = capsys.readouterr().err
    for line in ("sfm [1/3] features (36 images", "sfm [2/3] matching", "sfm [mapping] done",
                 "36/36 images registered"):
        assert line in err
    if matcher == "retrieval":
        assert "visual-word retrieval" in err and "sequential window" in err
    assert set(run_sfm.last_times) == {"features", "matching", "mapping"}
    assert model == tmp_path / "sparse" / "0"
    est = load_colmap(tmp_path, split="all")
    assert len(est) == len(truth) == 36  # every view registered
    assert est.points is not None and len(est.points) > 300
    errors = pose_errors([est.cameras[est.index(n)] for n in truth.names], truth.cameras)
    radius = np.linalg.norm(truth.cameras[0].center - [0.0, 0.0, 0.35])
    mean_rot = float(np.mean(errors["rotation_deg"]))
    print(f"SfM ({matcher}, {mapper}) on 36 orbit views at 128x96: {seconds:.1f} s; rotation error max "
          f"{errors['max_rotation_deg']:.2f} deg, mean {mean_rot:.2f} deg; centre error max "
          f"{errors['max_center'] / radius:.2%} of the orbit radius")
    max_rot, max_mean_rot, max_centre = TOLERANCES[matcher]
    assert errors["max_rotation_deg"] < max_rot and mean_rot < max_mean_rot
    assert errors["max_center"] < max_centre * radius


def test_pair_sets():
    assert pairs.sequential_pairs(5, overlap=2) == {(0, 1), (0, 2), (1, 2), (1, 3), (2, 3), (2, 4), (3, 4)}
    sim = -np.abs(np.subtract.outer(np.arange(8), np.arange(8))).astype(float)  # a line: neighbours are similar
    assert pairs.nearest_pairs(sim, 1) == {(i, i + 1) for i in range(7)}
    assert all(j > i for i, j in pairs.nearest_pairs(sim, 3)) and len(pairs.nearest_pairs(sim, 7)) == 28
    assert pairs.looks_sequential(sim)
    shuffled = np.random.default_rng(0).permutation(8)
    assert not pairs.looks_sequential(sim[np.ix_(shuffled, shuffled)], top=1)


def test_visual_words_tell_scenes_apart():
    """Images of two different 'scenes' (descriptors around two disjoint sets of patterns) are most similar to
    images of their own scene."""
    rng = np.random.default_rng(0)
    patterns = rng.integers(0, 256, (2, 40, 128))
    images = []
    for i in range(10):
        group = patterns[i % 2]
        picks = group[rng.integers(0, 40, 300)] + rng.normal(0, 8, (300, 128))
        images.append(np.clip(picks, 0, 255).astype(np.uint8))
    sim = pairs.word_similarity(images, words=64)
    np.fill_diagonal(sim, -np.inf)
    assert all(sim[i].argmax() % 2 == i % 2 for i in range(10))


def test_pose_neighbours_prefer_near_cameras_looking_the_same_way():
    centres = np.array([[0.0, 0, 0], [0.1, 0, 0], [5.0, 0, 0], [0.05, 0, 0]])
    forwards = np.array([[0.0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, -1]])  # the last one looks away
    sim = pairs.pose_similarity(centres, forwards)
    np.fill_diagonal(sim, -np.inf)
    assert sim[0].argmax() == 1 and sim[0, 3] < sim[0, 2]


def test_small_images_get_the_low_sift_threshold():
    # 368x640 video frames registered 403/464 with COLMAP's threshold and 454/464 with the low one
    # (benchmarks/results/sfm_stam464*.json); images above SMALL_IMAGE_SIDE keep COLMAP's default.
    from warpgs.data.sfm.features import SMALL_IMAGE_PEAK_THRESHOLD, SMALL_IMAGE_SIDE, default_peak_threshold

    assert default_peak_threshold(640) == SMALL_IMAGE_PEAK_THRESHOLD
    assert default_peak_threshold(SMALL_IMAGE_SIDE) == SMALL_IMAGE_PEAK_THRESHOLD
    assert default_peak_threshold(SMALL_IMAGE_SIDE + 1) is None
    assert default_peak_threshold(None) is None


@pytest.mark.parametrize("kwargs,match", [(dict(mapper="hierarchical"), "mapper"), (dict(matcher="vocab"), "matcher")])
def test_unknown_mapper_or_matcher_is_named_before_any_work(tmp_path, kwargs, match):
    shutil.copytree(synthetic_dir("orbit") / "images", tmp_path / "images")
    with pytest.raises(ValueError, match=match):
        run_sfm(tmp_path / "images", tmp_path / "out", **kwargs)
    assert not (tmp_path / "out").exists()  # nothing written
