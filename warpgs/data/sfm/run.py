"""Structure from motion through pycolmap for a folder of images without a model.

features (SIFT, images above 1600 px downscaled) -> matching (exhaustive for small sets; for larger ones each
image with its most similar ones by visual words, plus a sequential window when the names are in video order;
see data/sfm/pairs.py) -> incremental mapping, or global mapping (GLOMAP, `mapper="global"`). Every core is used
by default. Per-stage progress lines on stderr (warpgs.utils.progress.Stages). Output follows the COLMAP layout:
<out>/database.db and <out>/sparse/0 (the largest model).
"""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import Optional, Sequence

from warpgs.data.errors import MissingSceneFile, PathLike, SceneError
from warpgs.data.formats.image_io import image_size, list_images
from warpgs.data.sfm import features
from warpgs.data.sfm.features import MATCHERS, MAX_IMAGE_SIZE
from warpgs.utils.progress import Stages

STAGES = ("features", "matching", "mapping")
MAPPERS = ("incremental", "global")


def _mapping_options(num_threads: int, seed: int, refine_intrinsics: bool):
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = num_threads
    options.random_seed = seed
    options.ba_refine_focal_length = refine_intrinsics
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = refine_intrinsics
    return options


def _global_options(num_threads: int, seed: int, refine_intrinsics: bool):
    import pycolmap

    options = pycolmap.GlobalPipelineOptions()
    options.num_threads = num_threads
    options.random_seed = seed
    ba = options.mapper.bundle_adjustment
    ba.refine_focal_length = ba.refine_extra_params = refine_intrinsics
    ba.refine_principal_point = False
    return options


def _largest_first(sparse: Path, models: dict) -> int:
    """Put the model with the most registered images at sparse/0 (what the loaders read); returns its key."""
    best = max(models, key=lambda k: models[k].num_reg_images())
    if best != 0:
        tmp = sparse / "largest"
        (sparse / str(best)).rename(tmp)
        (sparse / "0").rename(sparse / str(best))
        tmp.rename(sparse / "0")
    return best


def run_sfm(image_dir: PathLike, out_dir: PathLike, *, matcher: str = "auto", camera_model: str = "SIMPLE_RADIAL",
            camera_params: Optional[Sequence[float]] = None, single_camera: bool = True, refine_intrinsics: bool = True,
            image_names: Optional[Sequence[str]] = None, peak_threshold: Optional[float] = None,
            max_image_size: int = MAX_IMAGE_SIZE, max_features: int = 8192, num_threads: int = -1, seed: int = 0,
            mapper: str = "incremental", progress: bool = True, quiet: bool = True) -> Path:
    """Reconstruct cameras and sparse points for the images in `image_dir`; returns <out_dir>/sparse/0.

    matcher: "auto" (exhaustive up to 60 images, else "retrieval"), "exhaustive", "sequential" (COLMAP's, for
    video frames; no loop detection, which needs a vocabulary-tree file) or "retrieval" (visual words built from
    the set's own features, plus a sequential window when the file names are in video order).
    camera_params: known intrinsics in `camera_model`'s COLMAP order (e.g. PINHOLE fx, fy, cx, cy); with
    refine_intrinsics=False they stay fixed, which makes small or low-texture sets far more reliable.
    max_image_size: larger images are downscaled for feature extraction (poses and intrinsics stay in pixels of
    the original images). num_threads: -1 uses every core; 1 makes runs reproducible (with `seed`).
    peak_threshold: SIFT detection threshold; default COLMAP's 0.0067, or 0.002 for images up to 1024 px
    (features.SMALL_IMAGE_SIDE), where the default finds too few features to register every view.
    mapper: "incremental" (COLMAP's) or "global" (GLOMAP: rotation averaging and global positioning, then one
    bundle adjustment; on a 292-photo capture 4.4x faster than incremental with every image registered,
    benchmarks/results/sfm_bonsai800_*.json; no per-image progress). Global is for ordered captures (video,
    orbits): on an internet-photo collection it registered every photo and posed half of them wrongly
    (sfm_liberty_global.json, checked against the author's poses).
    stage times end up in run_sfm.last_times (seconds per stage) for benchmarks.
    """
    import pycolmap

    image_dir, out_dir = Path(image_dir), Path(out_dir)
    if not image_dir.is_dir():
        raise MissingSceneFile(image_dir, "image folder")
    images = [p.name for p in list_images(image_dir)] if image_names is None else list(image_names)
    if len(images) < 2:
        raise SceneError(image_dir, f"SfM needs at least 2 images, found {len(images)}")
    if matcher not in MATCHERS:
        raise ValueError(f"matcher must be one of {MATCHERS}, got {matcher!r}")
    if mapper not in MAPPERS:
        raise ValueError(f"mapper must be one of {MAPPERS}, got {mapper!r}")
    out_dir.mkdir(parents=True, exist_ok=True)
    database = out_dir / "database.db"
    database.unlink(missing_ok=True)  # a stale database would mix old and new features
    sparse = out_dir / "sparse"
    shutil.rmtree(sparse, ignore_errors=True)
    sparse.mkdir(parents=True)
    if quiet:
        pycolmap.logging.minloglevel = 2  # warnings and errors only; our progress lines say what is happening
    pycolmap.set_random_seed(seed)
    stages = Stages(STAGES, prefix="sfm", enabled=progress)
    side = max(image_size(image_dir / images[0]))
    threads = num_threads if num_threads > 0 else pycolmap_threads()

    with stages.run("features", f"{len(images)} images, {side} px, max {max_image_size} px, {threads} threads"):
        reader = pycolmap.ImageReaderOptions(camera_model=camera_model)
        if camera_params is not None:
            reader.camera_params = ",".join(f"{p:.10g}" for p in camera_params)
        features.extract(database, image_dir, images, camera_mode="SINGLE" if single_camera else "AUTO",
                         reader=reader, max_image_size=max_image_size, largest_side=side,
                         peak_threshold=peak_threshold, max_features=max_features, num_threads=num_threads)

    used, names, pairs, detail = features.choose_pairs(database, matcher)
    with stages.run("matching", detail):
        features.match(database, used, names, pairs, out_dir, num_threads=num_threads)
    stages.report(f"{features.verified_pairs(database)} verified image pairs")

    registered = [2]  # the callback fires once per image added after the initial pair
    step = max(1, len(images) // 10)

    def on_next_image():
        registered[0] += 1
        if registered[0] % step == 0:
            stages.report(f"mapping: registered {min(registered[0], len(images))}/{len(images)}")

    with stages.run("mapping", "incremental" if mapper == "incremental" else "global (GLOMAP)"):
        if mapper == "global":
            models = pycolmap.global_mapping(database, image_dir, sparse,
                                             _global_options(num_threads, seed, refine_intrinsics))
        else:
            models = pycolmap.incremental_mapping(database, image_dir, sparse,
                                                  _mapping_options(num_threads, seed, refine_intrinsics),
                                                  next_image_callback=on_next_image)
    run_sfm.last_times = dict(stages.times)
    if not models:
        raise SceneError(image_dir, "SfM failed: no images could be registered (too little texture or overlap?)")
    best = models[_largest_first(sparse, models)]
    n_reg = best.num_reg_images()
    error = best.compute_mean_reprojection_error()
    stages.report(f"{n_reg}/{len(images)} images registered ({100 * n_reg / len(images):.1f}%), "
                  f"{best.num_points3D()} points, mean reprojection error {error:.2f} px"
                  + (f"; {len(models)} models, the largest is sparse/0" if len(models) > 1 else ""))
    if n_reg < 2:
        raise SceneError(image_dir, f"SfM registered only {n_reg} image(s)")
    return sparse / "0"


def pycolmap_threads() -> int:
    """What num_threads=-1 means to COLMAP: every core this process may use."""
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


run_sfm.last_times = {}
