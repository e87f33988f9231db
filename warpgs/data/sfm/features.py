"""SIFT features and matching into a COLMAP database (pycolmap, CPU), shared by SfM and by triangulation from
known poses. Images larger than max_image_size are downscaled for extraction (keypoints are stored in the
original pixel coordinates); every core is used unless num_threads says otherwise."""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from warpgs.data.sfm import pairs as pairing

MAX_IMAGE_SIZE = 1600
# Images up to this size get a lower SIFT threshold: COLMAP's default (0.0067) finds too few features on them. A
# 464-frame 368x640 video capture (benchmarks/sfm.py): a median of 599 features an image, 403 registered in 4
# models by default; 454 (97.8%) in one model with 0.002.
SMALL_IMAGE_SIDE = 1024
SMALL_IMAGE_PEAK_THRESHOLD = 0.002
MATCHERS = ("auto", "exhaustive", "sequential", "retrieval")


def default_peak_threshold(largest_side: Optional[int]) -> Optional[float]:
    """The SIFT threshold for images whose larger side is `largest_side` px (None: COLMAP's default)."""
    if largest_side is not None and largest_side <= SMALL_IMAGE_SIDE:
        return SMALL_IMAGE_PEAK_THRESHOLD
    return None


def extract(database: Path, image_dir: Path, names: Sequence[str], *, camera_mode: str = "SINGLE", reader=None,
            max_image_size: int = MAX_IMAGE_SIZE, largest_side: Optional[int] = None,
            peak_threshold: Optional[float] = None, max_features: int = 8192, num_threads: int = -1) -> None:
    """SIFT features of `names` (relative to image_dir) into `database`. largest_side: the images' largest side,
    which picks the low SIFT threshold for small images unless peak_threshold is given."""
    import pycolmap

    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = num_threads
    options.max_image_size = max_image_size
    options.sift.max_num_features = max_features
    if peak_threshold is None:
        peak_threshold = default_peak_threshold(largest_side)
    if peak_threshold is not None:
        options.sift.peak_threshold = peak_threshold
    pycolmap.extract_features(database, image_dir, image_names=list(names),
                              camera_mode=getattr(pycolmap.CameraMode, camera_mode),
                              reader_options=reader or pycolmap.ImageReaderOptions(), extraction_options=options,
                              device=pycolmap.Device.cpu)


def choose_pairs(database: Path, matcher: str = "auto", *, similarity: Optional[Callable[[list], np.ndarray]] = None,
                 neighbours: int = pairing.RETRIEVAL_NEIGHBOURS) -> tuple[str, Optional[list[str]], set, str]:
    """(matcher used, image names, pairs by name index or None for COLMAP's own pairing, description).

    "auto": exhaustive up to pairing.EXHAUSTIVE_MAX_IMAGES images, else "retrieval". "retrieval": each image with
    its `neighbours` most similar, by `similarity(names)` when given (e.g. from known poses) or else by visual
    words; plus a sequential window when the name order looks like a video."""
    import pycolmap

    if matcher not in MATCHERS:
        raise ValueError(f"matcher must be one of {MATCHERS}, got {matcher!r}")
    with pycolmap.Database.open(str(database)) as db:
        n = db.num_images()
    if matcher == "auto":
        matcher = "exhaustive" if n <= pairing.EXHAUSTIVE_MAX_IMAGES else "retrieval"
    if matcher == "exhaustive":
        return matcher, None, set(), f"exhaustive, {n * (n - 1) // 2} pairs"
    if matcher == "sequential":
        return matcher, None, set(), f"sequential (COLMAP, overlap {pairing.SEQUENTIAL_OVERLAP}, no loop detection)"
    if similarity is not None:
        with pycolmap.Database.open(str(database)) as db:
            names = sorted(im.name for im in db.read_all_images())
        sim, how = similarity(names), "pose neighbours"
    else:
        names, descriptors = pairing.read_descriptors(database)
        sim, how = pairing.word_similarity(descriptors), "visual-word retrieval"
    pairs = pairing.nearest_pairs(sim, neighbours)
    detail = f"{how}, {neighbours} per image"
    if similarity is None and pairing.looks_sequential(sim):
        pairs |= pairing.sequential_pairs(len(names))
        detail += f" + sequential window {pairing.SEQUENTIAL_OVERLAP} (name order looks like a video)"
    return matcher, names, pairs, f"{detail}, {len(pairs)} pairs"


def match(database: Path, matcher: str, names: Optional[list[str]], pairs: set, work_dir: Path, *,
          num_threads: int = -1, verification=None) -> None:
    """Match and geometrically verify the chosen pairs (see choose_pairs)."""
    import pycolmap

    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = num_threads
    kwargs = dict(matching_options=options, device=pycolmap.Device.cpu)
    if verification is not None:
        kwargs["verification_options"] = verification
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(database, **kwargs)
    elif matcher == "sequential":
        seq = pycolmap.SequentialPairingOptions()
        seq.overlap = pairing.SEQUENTIAL_OVERLAP
        seq.loop_detection = False  # needs a vocabulary-tree file
        pycolmap.match_sequential(database, pairing_options=seq, **kwargs)
    else:
        imported = pycolmap.ImportedPairingOptions()
        imported.match_list_path = str(pairing.write_pairs(Path(work_dir) / "pairs.txt", names, pairs))
        pycolmap.match_image_pairs(database, pairing_options=imported, **kwargs)


def verified_pairs(database: Path, min_inliers: int = 15) -> int:
    """Image pairs whose geometric verification kept at least min_inliers matches (COLMAP's default minimum)."""
    import pycolmap

    with pycolmap.Database.open(str(database)) as db:
        _, inliers = db.read_two_view_geometry_num_inliers()
    return int(np.sum(np.asarray(inliers) >= min_inliers))
