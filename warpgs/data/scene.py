"""The one scene type every loader returns: cameras, their split, optional SfM points, the scenes derived from it
(downscaled, re-split, other points or priors) and the per-view tensors the trainer consumes. Decoding the
per-view files into maps at the served resolution is warpgs.data.view_maps (a mixin of Scene)."""
from __future__ import annotations

import copy
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from warpgs.data.depth import files as depth_io

from warpgs.data.formats import image_io
from warpgs.data.extent import camera_radius
from warpgs.data.camera import Camera
from warpgs.data.errors import MissingSceneFile, SceneError
from warpgs.data.points import PointCloud
from warpgs.data.formats.resize import downscaled_size
from warpgs.data.formats.undistort import UndistortMap
from warpgs.data.view_maps import MapFormat, ViewMaps


@dataclass
class ViewFiles:
    """Files that belong to one view; everything but the image is optional."""

    image: Path
    depth: Optional[Path] = None  # measured or exact depth (camera z), for evaluation
    depth_prior: Optional[Path] = None  # monocular/stereo prior, used for supervision after alignment
    mask: Optional[Path] = None
    labels: Optional[Path] = None  # integer object ids, 0 = unlabelled
    features: Optional[Path] = None  # .npy [h, w, C] feature map (e.g. language features)


@dataclass
class View:
    """What the trainer consumes for one view (torch tensors, float32 unless stated)."""

    index: int
    name: str
    viewmat: torch.Tensor  # [4, 4] world -> camera
    K: torch.Tensor  # [3, 3]
    width: int
    height: int
    image: torch.Tensor  # [H, W, 3] in [0, 1]
    mask: Optional[torch.Tensor] = None  # [H, W, 1] bool, pixels to use
    inv_depth_prior: Optional[torch.Tensor] = None  # [H, W, 1]
    inv_depth_valid: Optional[torch.Tensor] = None  # [H, W, 1] bool
    inv_depth_confidence: Optional[torch.Tensor] = None  # [H, W, 1] in [0, 1], when the prior file carries one
    depth: Optional[torch.Tensor] = None  # [H, W, 1] reference depth; inf = sky, 0 = unknown
    labels: Optional[torch.Tensor] = None  # [H, W] int64
    features: Optional[torch.Tensor] = None  # [h, w, C]

    def to(self, device) -> "View":
        out = copy.copy(self)
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, torch.Tensor):
                setattr(out, f.name, value.to(device))
        return out


class Scene(ViewMaps):
    """Views of one scene. Public state:

    cameras         served cameras (undistorted, downscaled): what renders and the trainer use
    native_cameras  cameras as stored on disk
    files           ViewFiles per view;  train / test: view indices
    points          PointCloud (SfM points with the views observing them) or None
    label_names     {id: name} for label maps;  metadata: loader extras (e.g. "grid_positions")
    Per-view data: image(i), view(i) (all tensors for training), *_np(i) accessors returning numpy arrays (those
    decode the view's files: warpgs.data.view_maps).
    """

    def __init__(self, cameras: Sequence[Camera], files: Sequence[ViewFiles], *, root: Path,
                 train: Optional[Sequence[int]] = None, test: Optional[Sequence[int]] = None,
                 points: Optional[PointCloud] = None, label_names: Optional[dict] = None,
                 depth_format: MapFormat = MapFormat("depth"), prior_format: MapFormat = MapFormat(),
                 background: Optional[Sequence[float]] = None, undistort: bool = True, downscale: int = 1,
                 source: str = "", metadata: Optional[dict] = None):
        if len(cameras) != len(files):
            raise ValueError(f"{len(cameras)} cameras but {len(files)} view file sets")
        if not cameras:
            raise SceneError(root, "scene has no views")
        names = [c.name for c in cameras]
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise SceneError(root, f"duplicate view names {dup[:5]}")
        self.root = Path(root)
        self.native_cameras = list(cameras)  # as stored: full resolution, possibly distorted
        self.files = list(files)
        self.points = points
        self.label_names = dict(label_names or {})
        self.depth_format = depth_format
        self.prior_format = prior_format
        self.background = None if background is None else np.asarray(background, np.float32)
        self.undistort = undistort
        self.source = source
        self.metadata = dict(metadata or {})
        self.train = list(range(len(cameras))) if train is None else [int(i) for i in train]
        self.test = [] if test is None else [int(i) for i in test]
        self._check_split()
        if points is not None and points.observed_by is not None and len(points.observed_by) != len(cameras):
            raise SceneError(root, "point observations do not match the number of views")
        self._maps: dict[tuple, UndistortMap] = {}
        self._memory: dict = {}
        self._memory_bytes = 0
        self.downscale = 1
        self.cameras = list(cameras)
        self._set_downscale(downscale)

    # --- construction helpers ---------------------------------------------------------------------------------
    def _check_split(self):
        n = len(self.native_cameras)
        for name, idx in (("train", self.train), ("test", self.test)):
            bad = [i for i in idx if not 0 <= i < n]
            if bad:
                raise SceneError(self.root, f"{name} split refers to views {bad[:5]} but the scene has {n}")
        overlap = sorted(set(self.train) & set(self.test))
        if overlap:
            raise SceneError(self.root, f"views {[self.native_cameras[i].name for i in overlap[:5]]} are in both "
                                        f"train and test")

    def _set_downscale(self, factor: int):
        self.downscale = factor
        self.cameras = []
        for i, cam in enumerate(self.native_cameras):
            base = self._undistorted_camera(i) if self._needs_undistort(cam) else cam
            w, h = downscaled_size(base.width, base.height, factor)
            self.cameras.append(base.scaled(w, h) if factor != 1 else base)
        self._memory, self._memory_bytes = {}, 0

    def _needs_undistort(self, cam: Camera) -> bool:
        return self.undistort and cam.has_distortion

    def _undistort_map(self, i: int) -> UndistortMap:
        """Views sharing intrinsics share one map: it depends on the lens, not on the pose."""
        cam = self.native_cameras[i]
        key = (cam.model, cam.width, cam.height, tuple(cam.K.ravel()), cam.distortion)
        if key not in self._maps:
            self._maps[key] = UndistortMap.for_camera(cam)
        return self._maps[key]

    def _undistorted_camera(self, i: int) -> Camera:
        cam, target = self.native_cameras[i], self._undistort_map(i).target
        return replace(cam, K=target.K, width=target.width, height=target.height, model="PINHOLE", distortion=())

    def _copy(self) -> "Scene":
        out = copy.copy(self)
        out._memory, out._memory_bytes = {}, 0
        out._maps = dict(self._maps)
        out.metadata = dict(self.metadata)
        return out

    def downscaled(self, factor: int) -> "Scene":
        """The same scene served at 1/factor resolution (factor in 1, 2, 4, 8); intrinsics scale accordingly."""
        out = self._copy()
        out._set_downscale(factor)
        return out

    def with_split(self, train: Sequence[int], test: Sequence[int]) -> "Scene":
        out = self._copy()
        out.train, out.test = [int(i) for i in train], [int(i) for i in test]
        out._check_split()
        return out

    def with_points(self, points: Optional[PointCloud]) -> "Scene":
        """The same views with other SfM points (e.g. triangulated from the training views only)."""
        if points is not None and points.observed_by is not None and len(points.observed_by) != len(self.cameras):
            raise ValueError(f"points: observations for {len(points.observed_by)} views, the scene has "
                             f"{len(self.cameras)}")
        out = self._copy()
        out.points = points
        return out

    def with_depth_priors(self, folder: Path, fmt: MapFormat = MapFormat()) -> "Scene":
        """Attach per-view depth priors found in `folder` (by image stem); views without a file get none."""
        folder = Path(folder)
        if not folder.is_dir():
            raise MissingSceneFile(folder, "depth prior folder")
        out = self._copy()
        out.files = [copy.copy(f) for f in self.files]
        for cam, f in zip(self.native_cameras, out.files):
            f.depth_prior = image_io.find_sibling(folder, cam.name, depth_io.DEPTH_EXTENSIONS)
        out.prior_format = fmt
        return out

    # --- basic facts ------------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no view named {name!r} in {self.root}") from None

    def camera(self, i: int) -> Camera:
        return self.cameras[i]

    def has(self, what: str, views: Optional[Sequence[int]] = None) -> bool:
        """Whether any view (of `views`, default all) has a file of this kind: depth, depth_prior, mask, labels,
        features."""
        files = self.files if views is None else [self.files[v] for v in views]
        return any(getattr(f, what) is not None for f in files)

    def camera_extent(self) -> float:
        """Radius of the training cameras' centres around their mean, times 1.1 (the usual 3DGS scene scale,
        getNerfppNorm over the training cameras: held-out cameras must not set a run's learning rates; on fern
        with 3 training views the extent of all 20 cameras is twice theirs). All cameras when none trains."""
        radius = camera_radius([self.cameras[i] for i in self.train] or self.cameras)
        return 1.1 * radius if radius > 0 else 1.0

    def summary(self) -> str:
        cam = self.cameras[0]
        extras = [k for k in ("depth", "depth_prior", "mask", "labels", "features") if self.has(k)]
        counts = ", ".join(f"{k} {sum(getattr(f, k) is not None for f in self.files)}/{len(self)}" for k in extras)
        pts = f"{len(self.points)} points" if self.points is not None else "no points"
        return (f"{self.source or 'scene'} at {self.root}: {len(self)} views ({len(self.train)} train, "
                f"{len(self.test)} test"
                + (f", {len(self.metadata['excluded'])} left out" if self.metadata.get("excluded") else "")
                + f"), {cam.width}x{cam.height} (1/{self.downscale}), {pts}"
                + (f"; {counts}" if counts else ""))

    # --- torch views --------------------------------------------------------------------------------------------
    def view(self, i: int, device=None) -> View:
        cam = self.cameras[i]
        t = lambda a: None if a is None else torch.from_numpy(np.ascontiguousarray(a)).to(device)  # noqa: E731
        prior = self.inv_depth_prior_np(i)
        confidence = None if prior is None else self.prior_confidence_np(i)
        depth = self.depth_np(i)
        mask = self.mask_np(i)
        return View(index=i, name=cam.name, viewmat=cam.viewmat_tensor(device), K=cam.K_tensor(device),
                    width=cam.width, height=cam.height, image=self.image(i, device),
                    mask=None if mask is None else t(mask[..., None]),
                    inv_depth_prior=None if prior is None else t(prior[0][..., None]),
                    inv_depth_valid=None if prior is None else t(prior[1][..., None]),
                    inv_depth_confidence=None if confidence is None else t(confidence[..., None]),
                    depth=None if depth is None else t(depth[0][..., None]),
                    labels=t(self.labels_np(i)), features=t(self.features_np(i)))

    def train_views(self, device=None) -> list[View]:
        return [self.view(i, device) for i in self.train]

    def test_views(self, device=None) -> list[View]:
        return [self.view(i, device) for i in self.test]

    # --- points -------------------------------------------------------------------------------------------------
    def visible_points(self, i: int) -> np.ndarray:
        """Indices of the scene points seen by view i: its SfM track observations when it has any; otherwise
        (no tracks, or a view SfM never used, such as a held-out view) the points in front of the camera that
        project inside the image, without an occlusion test."""
        if self.points is None:
            return np.zeros(0, dtype=np.int64)
        if self.points.observed_by is not None and len(self.points.observed_by[i]):
            return self.points.observed_by[i]
        cam = self.cameras[i]
        pix, z = cam.project(self.points.xyz)
        inside = (z > 0) & (pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0) & (pix[:, 1] < cam.height)
        return np.nonzero(inside)[0]

    # --- checks -------------------------------------------------------------------------------------------------
    def validate(self, decode: bool = False) -> "Scene":
        """Check that every referenced file exists and has the right size (header only unless `decode`).

        decode=True reads every map fully, so truncated files and NaN depths surface now rather than mid-training.
        """
        for i, (cam, f) in enumerate(zip(self.native_cameras, self.files)):
            w, h = image_io.image_size(f.image, "image")
            if (w, h) != (cam.width, cam.height):
                raise SceneError(f.image, f"image is {w}x{h} but its camera says {cam.width}x{cam.height}")
            for what in ("depth", "depth_prior", "mask", "labels", "features"):
                path = getattr(f, what)
                if path is not None and not Path(path).is_file():
                    raise MissingSceneFile(path, what.replace("_", " "))
            if decode:
                self.image_np(i)
                self.mask_np(i)
                self.depth_np(i)
                self.inv_depth_prior_np(i)
                self.labels_np(i)
                self.features_np(i)
        return self
