"""Optional learned depth: a video depth model run over the views as a pseudo-video.

The sparse-view light-field method feeds the sub-aperture images to a video depth model in a serpentine
order, so consecutive frames are neighbours and the model's temporal consistency becomes cross-view
consistency. Its output is relative (affine-invariant inverse depth), so priors from it must be aligned to
the SfM points (warpgs.data.depth.priors does that). Nothing here downloads anything: the package and the
checkpoint must already be on this machine, otherwise DepthModelUnavailable says exactly what is missing.
"""
from __future__ import annotations

import importlib.util
from abc import abstractmethod
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from warpgs.data.depth.estimators import DepthEstimate, DepthEstimator
from warpgs.data.errors import DepthModelUnavailable, PathLike
from warpgs.data.formats.image_io import to_uint8
from warpgs.data.formats.lightfield import pseudo_video_order
from warpgs.data.formats.resize import resize_area


def chain_order(centres: np.ndarray) -> list[int]:
    """Greedy nearest-neighbour path through camera centres, starting from the first view."""
    n = len(centres)
    order, left = [0], set(range(1, n))
    while left:
        last = centres[order[-1]]
        nxt = min(left, key=lambda j: float(np.linalg.norm(centres[j] - last)))
        order.append(nxt)
        left.remove(nxt)
    return order


class PseudoVideoDepth(DepthEstimator):
    """Base for learned video models: orders the views, batches them as frames, returns relative inverse depth."""

    output = "inverse_depth"  # what predict_video returns: "inverse_depth" (disparity) or "depth"

    def frame_order(self, scene, views: Sequence[int]) -> list[int]:
        views = list(views)
        positions = scene.metadata.get("grid_positions") or {}
        names = [scene.names[v] for v in views]
        if positions and all(positions.get(n) is not None for n in names):
            return [views[i] for i in pseudo_video_order({n: positions[n] for n in names}, names)]
        return [views[i] for i in chain_order(np.stack([scene.cameras[v].center for v in views]))]

    @abstractmethod
    def predict_video(self, frames: np.ndarray) -> np.ndarray:
        """frames [N, H, W, 3] uint8 RGB -> [N, h, w] float (relative inverse depth or depth, see `output`)."""

    def estimate(self, scene, views: Sequence[int], sources: Optional[Sequence[int]] = None) -> dict[int, DepthEstimate]:
        order = self.frame_order(scene, views)
        sizes = {(scene.cameras[v].height, scene.cameras[v].width) for v in order}
        if len(sizes) != 1:
            raise ValueError(f"{self.name}: pseudo-video frames must share one size, got {sorted(sizes)}")
        frames = np.stack([to_uint8(scene.image_np(v)[0]) for v in order])
        pred = np.asarray(self.predict_video(frames), dtype=np.float32)
        if pred.ndim != 3 or len(pred) != len(order):
            raise ValueError(f"{self.name}: expected {len(order)} depth frames, got shape {pred.shape}")
        out = {}
        for v, p in zip(order, pred):
            cam = scene.cameras[v]
            p = resize_area(p, cam.width, cam.height)
            if self.output == "depth":
                valid = np.isfinite(p) & (p > 0)
                p = np.where(valid, 1.0 / np.where(valid, p, 1.0), 0.0)
            valid = np.isfinite(p) & (p > 0)
            out[v] = DepthEstimate(inv_depth=np.where(valid, p, 0.0).astype(np.float32), valid=valid, metric=False)
        return out


# Architecture hyper-parameters of the released checkpoints (needed to build the network before loading).
_ENCODERS = {"vits": {"features": 64, "out_channels": [48, 96, 192, 384]},
             "vitb": {"features": 128, "out_channels": [96, 192, 384, 768]},
             "vitl": {"features": 256, "out_channels": [256, 512, 1024, 1024]}}
_PACKAGE = "video_depth_anything"


class VideoDepthAnything(PseudoVideoDepth):
    """Adapter for Video Depth Anything (relative model): needs its `video_depth_anything` package importable
    (a clone of github.com/DepthAnything/Video-Depth-Anything on PYTHONPATH) and a local checkpoint file."""

    name = "video_depth_anything"

    def __init__(self, checkpoint: PathLike, encoder: str = "vits", input_size: int = 518, device: Optional[str] = None):
        if encoder not in _ENCODERS:
            raise ValueError(f"encoder must be one of {sorted(_ENCODERS)}, got {encoder!r}")
        if importlib.util.find_spec(_PACKAGE) is None:
            raise DepthModelUnavailable(
                f"Video Depth Anything is not installed: the package {_PACKAGE!r} cannot be imported. Clone "
                "https://github.com/DepthAnything/Video-Depth-Anything and add it to PYTHONPATH, or use the built-in "
                "PlaneSweepStereo estimator, which needs no weights.")
        self.checkpoint = Path(checkpoint)
        if not self.checkpoint.is_file():
            raise DepthModelUnavailable(
                f"{self.checkpoint}: Video Depth Anything checkpoint not found (expected e.g. "
                f"video_depth_anything_{encoder}.pth, downloaded beforehand); nothing is fetched automatically.")
        self.encoder, self.input_size = encoder, input_size
        self.device = device
        self._model = None

    def _load(self):
        import torch
        from video_depth_anything.video_depth import VideoDepthAnything as Net  # the optional package

        device = self.device or ("cuda" if torch.cuda.is_available() else "cpu")
        net = Net(encoder=self.encoder, **_ENCODERS[self.encoder])
        net.load_state_dict(torch.load(self.checkpoint, map_location="cpu", weights_only=True), strict=True)
        self._model, self.device = net.to(device).eval(), device
        return self._model

    def predict_video(self, frames: np.ndarray) -> np.ndarray:
        model = self._model or self._load()
        depths, _ = model.infer_video_depth(frames, 30, input_size=self.input_size, device=self.device)
        return np.stack(depths)
