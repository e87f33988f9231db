"""Structure from motion through pycolmap for a folder of images without a model.

feature extraction -> exhaustive or sequential matching -> incremental mapping, with a one-line progress
display on stderr. Output follows the COLMAP layout: <out>/database.db and <out>/sparse/0 (the largest model).
"""
from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

from warpgs.data.errors import MissingSceneFile, PathLike, SceneError
from warpgs.data.formats.image_io import image_size, list_images

MATCHERS = ("exhaustive", "sequential")
SMALL_IMAGE_SIDE = 1000
SMALL_IMAGE_PEAK_THRESHOLD = 0.002


class Progress:
    """Progress on stderr: one rewritten line on a terminal, one line per stage (and the result) in a log."""

    def __init__(self, enabled: bool = True, stream=None):
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.live = enabled and hasattr(self.stream, "isatty") and self.stream.isatty()
        self.start = time.perf_counter()
        self.stage = ""

    def _line(self, detail: str) -> str:
        return f"[sfm {self.stage}] {detail}, {time.perf_counter() - self.start:.1f} s"

    def step(self, stage: str, detail: str = ""):
        self.stage = stage
        if self.enabled and not self.live:
            self.stream.write(self._line(detail) + "\n")
            self.stream.flush()
        self.update(detail)

    def update(self, detail: str = ""):
        if self.live:
            self.stream.write("\r" + self._line(detail).ljust(72))
            self.stream.flush()

    def done(self, detail: str):
        if self.enabled:
            self.stream.write(("\r" if self.live else "") + self._line(detail).ljust(72) + "\n")
            self.stream.flush()


def run_sfm(image_dir: PathLike, out_dir: PathLike, *, matcher: str = "exhaustive", camera_model: str = "SIMPLE_RADIAL",
            camera_params: Optional[Sequence[float]] = None, single_camera: bool = True, refine_intrinsics: bool = True,
            image_names: Optional[Sequence[str]] = None, peak_threshold: Optional[float] = None,
            num_threads: int = -1, seed: int = 0, progress: bool = True, quiet: bool = True) -> Path:
    """Reconstruct cameras and sparse points for the images in `image_dir`; returns <out_dir>/sparse/0.

    camera_params: known intrinsics in `camera_model`'s COLMAP order (e.g. PINHOLE fx, fy, cx, cy); with
    refine_intrinsics=False they stay fixed, which makes small or low-texture sets far more reliable.
    num_threads: -1 uses every core; 1 makes runs reproducible (with `seed`), which multi-threaded ones are not.
    peak_threshold: SIFT detection threshold; default COLMAP's 0.0067, or 0.002 for images under 1000 px,
    where the default finds too few features to register every view.
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
    out_dir.mkdir(parents=True, exist_ok=True)
    database = out_dir / "database.db"
    database.unlink(missing_ok=True)  # a stale database would mix old and new features
    sparse = out_dir / "sparse"
    shutil.rmtree(sparse, ignore_errors=True)
    sparse.mkdir(parents=True)
    if quiet:
        pycolmap.logging.minloglevel = 2  # warnings and errors only; our progress line says what is happening
    pycolmap.set_random_seed(seed)
    bar = Progress(progress)

    bar.step("1/3 features", f"{len(images)} images")
    reader = pycolmap.ImageReaderOptions(camera_model=camera_model)
    if camera_params is not None:
        reader.camera_params = ",".join(f"{p:.10g}" for p in camera_params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    if peak_threshold is None and max(image_size(image_dir / images[0])) < SMALL_IMAGE_SIDE:
        peak_threshold = SMALL_IMAGE_PEAK_THRESHOLD
    if peak_threshold is not None:
        extraction.sift.peak_threshold = peak_threshold
    pycolmap.extract_features(database, image_dir, image_names=images,
                              camera_mode=pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.AUTO,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)

    bar.step("2/3 matching", f"{matcher} over {len(images)} images")
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pycolmap.match_sequential(database, matching_options=matching, device=pycolmap.Device.cpu)

    bar.step("3/3 mapping", "initialising")
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = num_threads
    options.random_seed = seed
    options.ba_refine_focal_length = refine_intrinsics
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = refine_intrinsics
    registered = [2]  # the callback fires once per image added after the initial pair

    def on_next_image():
        registered[0] += 1
        bar.update(f"registering image {min(registered[0], len(images))}/{len(images)}")

    models = pycolmap.incremental_mapping(database, image_dir, sparse, options, next_image_callback=on_next_image)
    if not models:
        raise SceneError(image_dir, "SfM failed: no images could be registered (too little texture or overlap?)")
    best = max(models, key=lambda k: models[k].num_reg_images())
    if best != 0:  # the trainer reads sparse/0: put the largest model there
        tmp = sparse / "largest"
        (sparse / str(best)).rename(tmp)
        (sparse / "0").rename(sparse / str(best))
        tmp.rename(sparse / "0")
    n_reg = models[best].num_reg_images()
    bar.done(f"{n_reg}/{len(images)} images registered, {models[best].num_points3D()} points")
    if n_reg < 2:
        raise SceneError(image_dir, f"SfM registered only {n_reg} image(s)")
    return sparse / "0"
