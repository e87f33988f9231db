"""Per-view maps of a Scene, decoded from its files at the served resolution (the ViewMaps mixin).

Per-pixel files (images, depth, depth priors, masks, labels) are stored at the cameras' native resolution and
possibly with lens distortion. Each read goes: check size -> undistort (if the camera has distortion and the
scene undistorts) -> downscale -> return. Images that needed undistorting or resizing are cached on disk as
PNG, so a factor-8 view of a 4K dataset is decoded from a small file after the first epoch; decoded maps are kept
in memory up to a budget.

The mixin reads the Scene's state: root, files, native_cameras, cameras, downscale, background, label_names,
depth_format, prior_format, _memory / _memory_bytes (the in-memory cache) and its undistortion helpers
(_needs_undistort, _undistort_map, _undistorted_camera).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from warpgs.data.cache import cache_dir, file_key, touch
from warpgs.data.depth import files as depth_io
from warpgs.data.errors import MissingSceneFile, SceneError
from warpgs.data.formats import image_io
from warpgs.data.formats.resize import (DOWNSCALE_FACTORS, downscaled_size, resize_area, resize_bilinear, resize_masked,
                                        resize_nearest)

_MEMORY_BUDGET_BYTES = 1 << 30
_MEMORY_LOCK = threading.Lock()  # views may be loaded from several threads (TrainViews.load_all)


@dataclass
class MapFormat:
    """How to read a family of depth files: what they store and a unit scale (e.g. 0.001 for millimetres)."""

    kind: Optional[str] = None  # "depth" | "inverse_depth" | None (the file declares it)
    scale: float = 1.0


class ViewMaps:
    """The *_np(i) accessors of Scene (and image(i)): one view's file decoded, undistorted and resized."""

    def _check_size(self, i: int, path: Path, shape: tuple, what: str) -> str:
        """'native' if the map matches the stored camera (may need undistorting), 'undistorted' if it matches the
        undistorted camera at any downscale factor (only needs resizing); otherwise an error naming the file."""
        native = self.native_cameras[i]
        h, w = shape[:2]
        if (w, h) == (native.width, native.height):
            return "native"
        base = self._undistorted_camera(i) if self._needs_undistort(native) else native
        sizes = [downscaled_size(base.width, base.height, f) for f in DOWNSCALE_FACTORS]
        if (w, h) in sizes:
            return "undistorted"
        raise SceneError(path, f"{what} is {w}x{h} but view {native.name!r} is {native.width}x{native.height}"
                               f" (or a 1/2, 1/4, 1/8 downscale of {base.width}x{base.height})")

    def _to_final(self, i: int, arr: np.ndarray, stage: str, kind: str,
                  valid: Optional[np.ndarray] = None) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """Undistort (native stage only) and resize a map; kind is 'colour', 'ids' or 'masked'."""
        cam = self.cameras[i]
        if stage == "native" and self._needs_undistort(self.native_cameras[i]):
            umap = self._undistort_map(i)
            if kind == "masked":
                # Nearest neighbour keeps invalid pixels from bleeding into valid ones.
                arr, valid = umap.apply(np.where(valid, arr, 0), nearest=True), umap.apply(valid, nearest=True)
                valid = valid & umap.coverage()
            else:
                arr = umap.apply(arr, nearest=(kind == "ids"))
        if arr.shape[:2] == (cam.height, cam.width):
            return arr, valid
        upsampling = arr.shape[0] < cam.height
        if kind == "ids" or (upsampling and kind == "masked"):
            return resize_nearest(arr, cam.width, cam.height), (
                None if valid is None else resize_nearest(valid, cam.width, cam.height))
        if kind == "colour":
            return (resize_bilinear(arr, cam.width, cam.height) if upsampling
                    else resize_area(arr, cam.width, cam.height)), None
        return resize_masked(arr, valid, cam.width, cam.height)

    def _remember(self, key, value):
        size = sum(v.nbytes for v in value if isinstance(v, np.ndarray)) if isinstance(value, tuple) else value.nbytes
        with _MEMORY_LOCK:
            if key not in self._memory and self._memory_bytes + size <= _MEMORY_BUDGET_BYTES:
                self._memory[key] = value
                self._memory_bytes += size
        return value

    def image_np(self, i: int) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """(rgb [H, W, 3] float32, alpha [H, W] or None) at the served resolution."""
        if ("image", i) in self._memory:
            return self._memory[("image", i)]
        path = self.files[i].image
        native, cam = self.native_cameras[i], self.cameras[i]
        needs_undistort = self._needs_undistort(native)
        if self.downscale != 1 and not needs_undistort:
            # LLFF / Mip-NeRF 360 ship images_2, images_4, images_8: use them when their size is exactly right.
            shipped = self.root / f"images_{self.downscale}" / native.name
            if shipped.is_file() and image_io.image_size(shipped) == (cam.width, cam.height):
                return self._remember(("image", i), image_io.read_image(shipped, self.background))
        cached = self._disk_cache_path(i) if (self.downscale != 1 or needs_undistort) else None
        if cached is not None and cached.is_file():
            rgb, _ = image_io.read_image(cached)
            alpha_path = cached.with_suffix(".alpha.png")
            alpha = image_io.read_mask_values(alpha_path) if alpha_path.is_file() else None
            if rgb.shape[:2] == (cam.height, cam.width):
                touch(cached)  # used now (warpgs-cache drops the least recently used entries first)
                return self._remember(("image", i), (rgb, alpha))
        rgb, alpha = image_io.read_image(path, self.background)
        if rgb.shape[:2] != (native.height, native.width):
            raise SceneError(path, f"image is {rgb.shape[1]}x{rgb.shape[0]} but its camera says "
                                   f"{native.width}x{native.height}")
        rgb, _ = self._to_final(i, rgb, "native", "colour")
        if alpha is not None:
            alpha, _ = self._to_final(i, alpha, "native", "colour")
        if cached is not None:  # served as the 8-bit cache file will serve it: the same values in every run
            rgb = image_io.to_float(image_io.to_uint8(rgb))
            if alpha is not None:
                image_io.write_png(cached.with_suffix(".alpha.png"), alpha)
            image_io.write_png(cached, rgb)  # written last: its presence means the entry is complete
        return self._remember(("image", i), (rgb, alpha))

    def _disk_cache_path(self, i: int) -> Path:
        path = self.files[i].image
        native = self.native_cameras[i]
        key = file_key(path, self.downscale, self._needs_undistort(native), native.model, native.distortion,
                       tuple(native.K.ravel()), None if self.background is None else tuple(self.background))
        return cache_dir() / "images" / key[:2] / f"{key}.png"

    def image(self, i: int, device=None) -> torch.Tensor:
        """[H, W, 3] float32 in [0, 1]."""
        return torch.from_numpy(self.image_np(i)[0]).to(device)

    def mask_np(self, i: int) -> Optional[np.ndarray]:
        """[H, W] bool from masks/, else from the image's alpha, else None."""
        f = self.files[i]
        if f.mask is not None:
            raw = image_io.read_mask(f.mask)
            stage = self._check_size(i, f.mask, raw.shape, "mask")
            return self._to_final(i, raw.astype(np.float32), stage, "colour")[0] >= 0.5
        alpha = self.image_np(i)[1]
        return None if alpha is None else alpha >= 0.5

    def depth_np(self, i: int) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """Reference depth (camera z): ([H, W] float32 with +inf for sky, valid [H, W] bool) or None."""
        f = self.files[i]
        if f.depth is None:
            return None
        inv, valid = self._inverse_depth(i, f.depth, self.depth_format, "depth map")
        with np.errstate(divide="ignore"):
            return np.where(valid, 1.0 / inv, 0.0).astype(np.float32), valid

    def inv_depth_prior_np(self, i: int) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """Inverse-depth prior ([H, W] float32, valid [H, W] bool) or None."""
        f = self.files[i]
        if f.depth_prior is None:
            return None
        return self._inverse_depth(i, f.depth_prior, self.prior_format, "depth prior")

    def prior_confidence_np(self, i: int) -> Optional[np.ndarray]:
        """The depth prior's per-pixel confidence ([H, W] float32 in [0, 1], 0 where the prior is invalid), or None
        when its file carries none (EXR priors written by compute_depth_priors keep it in a `confidence` channel)."""
        from warpgs.data.depth.estimators import CONFIDENCE_CHANNEL

        f = self.files[i]
        if f.depth_prior is None or Path(f.depth_prior).suffix.lower() != ".exr":
            return None
        key = ("prior confidence", i)
        if key in self._memory:
            return self._memory[key] if self._memory[key].size else None  # empty: the file has no such channel
        channels = depth_io.read_exr_channels(f.depth_prior)
        conf = channels.get(CONFIDENCE_CHANNEL)
        if conf is None:
            self._remember(key, np.zeros(0, np.float32))
            return None
        if conf.ndim != 2 or not np.all(np.isfinite(conf)) or conf.min() < 0 or conf.max() > 1:
            raise SceneError(f.depth_prior, f"channel {CONFIDENCE_CHANNEL!r} must be a finite [H, W] map in [0, 1]")
        raw_valid = channels.get("valid", conf)
        if raw_valid.shape != conf.shape:
            raise SceneError(f.depth_prior, f"channels 'valid' {raw_valid.shape} and {CONFIDENCE_CHANNEL!r} "
                                            f"{conf.shape} differ in size")
        stage = self._check_size(i, f.depth_prior, conf.shape, "depth prior confidence")
        conf, valid = self._to_final(i, conf, stage, "masked", raw_valid > 0.5)
        return self._remember(key, np.where(valid, np.clip(conf, 0.0, 1.0), 0.0).astype(np.float32))

    def _inverse_depth(self, i: int, path: Path, fmt: MapFormat, what: str) -> tuple[np.ndarray, np.ndarray]:
        key = (what, i)
        if key in self._memory:
            return self._memory[key]
        inv, valid = depth_io.read_inverse_depth(path, fmt.kind, fmt.scale)
        stage = self._check_size(i, path, inv.shape, what)
        return self._remember(key, self._to_final(i, inv, stage, "masked", valid))

    def labels_np(self, i: int) -> Optional[np.ndarray]:
        f = self.files[i]
        if f.labels is None:
            return None
        raw = image_io.read_label_map(f.labels)
        stage = self._check_size(i, f.labels, raw.shape, "label map")
        labels = self._to_final(i, raw, stage, "ids")[0]
        unknown = sorted(set(np.unique(labels).tolist()) - set(self.label_names) - {0}) if self.label_names else []
        if unknown:
            raise SceneError(f.labels, f"label ids {unknown[:10]} have no name in the scene's label list")
        return labels

    def features_np(self, i: int) -> Optional[np.ndarray]:
        """Feature map [h, w, C] float32 as stored (its resolution is the feature extractor's)."""
        f = self.files[i]
        if f.features is None:
            return None
        try:
            arr = np.load(f.features, allow_pickle=False)
        except FileNotFoundError:
            raise MissingSceneFile(f.features, "feature map") from None
        except (ValueError, OSError, EOFError) as exc:
            raise SceneError(f.features, f"unreadable or truncated feature map ({exc})") from exc
        if arr.ndim != 3:
            raise SceneError(f.features, f"feature map must be [h, w, C], got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise SceneError(f.features, "feature map contains NaN or Inf")
        return arr.astype(np.float32)
