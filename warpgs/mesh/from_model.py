"""Mesh a trained model: render depth and colour from the training cameras, fuse them into a sparse TSDF volume,
marching cubes, clean-up. Surfels render their median depth (the 2DGS choice: the depth where the accumulated
opacity crosses one half, a sharp surface); 3D Gaussians only have the expected (alpha-weighted mean) depth,
which is blurred across depth edges and floaters, so their meshes are worse."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from warpgs.mesh.clean import drop_degenerate_faces, remove_small_components
from warpgs.mesh.volume import Bound, Mesh, SparseTSDFVolume

DEFAULT_RESOLUTION = 512  # voxels across the bound's cube when --voxel is not given (2DGS's default mesh_res 1024
# spans twice the radius as well; half of it keeps a CPU run short)
TRUNC_VOXELS = 4.0  # default truncation: this many voxels
# Which rendered depth is fused. Surfels' expected depth meshed worse than their median on the benchmark's scene
# (docs/mesh.md), so it is there for comparison only.
DEPTH_OUTPUTS = {"median": "median_depth", "expected": "depth"}


@dataclass
class MeshSettings:
    voxel: Optional[float] = None  # world length; default 2 radius / DEFAULT_RESOLUTION
    trunc: Optional[float] = None  # default TRUNC_VOXELS voxels
    depth_trunc: Optional[float] = None  # ignore depth beyond this; default 2 radius (bounded), none (unbounded)
    radius: Optional[float] = None  # the bound's half-size; default the training cameras' extent
    centre: Optional[Sequence[float]] = None  # the bound's centre; default the training cameras' mean centre
    unbounded: bool = False  # contract the world outside the radius into the volume (background too)
    alpha_min: float = 0.5  # pixels less opaque than this carry no depth
    min_component: float = 0.01  # drop connected pieces with fewer faces than this fraction of the largest
    min_weight: float = 1.0  # a voxel counts once this many views saw it
    depth: Optional[str] = None  # "median" or "expected"; None: the kind's own (median for surfels)
    timings: dict = field(default_factory=dict)

    def check(self) -> None:
        for name in ("voxel", "trunc", "depth_trunc", "radius"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value > 0):
                flag = "--" + name.replace("_", "-")
                raise ValueError(f"{flag}: expected a positive length, got {value}")
        if self.centre is not None and (np.shape(self.centre) != (3,) or not np.isfinite(self.centre).all()):
            raise ValueError(f"--center: expected three finite numbers x,y,z, got {self.centre}")
        if not 0.0 <= self.alpha_min < 1.0:
            raise ValueError(f"--alpha-min: expected a value in [0, 1), got {self.alpha_min}")
        if self.depth is not None and self.depth not in DEPTH_OUTPUTS:
            raise ValueError(f"--depth: expected one of {sorted(DEPTH_OUTPUTS)}, got {self.depth!r}")
        if not 0.0 <= self.min_component <= 1.0:
            raise ValueError(f"--min-component: expected a fraction in [0, 1], got {self.min_component}")


def make_volume(settings: MeshSettings, centre: np.ndarray, radius: float, device: str) -> SparseTSDFVolume:
    settings.check()
    radius = settings.radius or radius
    centre = np.asarray(centre if settings.centre is None else settings.centre, dtype=np.float64)
    voxel = settings.voxel or 2.0 * radius / DEFAULT_RESOLUTION
    trunc = settings.trunc or TRUNC_VOXELS * voxel
    depth_max = settings.depth_trunc or (np.inf if settings.unbounded else 2.0 * radius)
    return SparseTSDFVolume(Bound(centre, radius, settings.unbounded), voxel, trunc, depth_max=depth_max,
                            device=device)


def finish_mesh(volume: SparseTSDFVolume, settings: MeshSettings) -> Mesh:
    t0 = time.perf_counter()
    mesh = volume.extract_mesh(settings.min_weight)
    settings.timings["marching_cubes_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    mesh = remove_small_components(drop_degenerate_faces(mesh), settings.min_component)
    settings.timings["clean_s"] = time.perf_counter() - t0
    return mesh


def fuse_depth_maps(frames: Sequence, settings: MeshSettings, centre: np.ndarray, radius: float,
                    device: str = "cpu") -> Mesh:
    """frames: (depth [H, W], colour [H, W, 3] or None, K, viewmat) per view, e.g. exact depth maps."""
    volume = make_volume(settings, centre, radius, device)
    t0 = time.perf_counter()
    for depth, color, K, viewmat in frames:
        volume.integrate(depth, K, viewmat, color)
    settings.timings["fusion_s"] = time.perf_counter() - t0
    return finish_mesh(volume, settings)


def mesh_trainer(trainer, settings: MeshSettings, device: Optional[str] = None,
                 report: Optional[Callable[[str], None]] = None) -> Mesh:
    """Render every training view of a loaded run (warpgs.cli.commands.load_run) and fuse it."""
    import torch

    from warpgs.cli.commands import _CameraView
    from warpgs.model.maps import depth_output

    scene = trainer.scene
    cams = [scene.cameras[i] for i in scene.train] or list(scene.cameras)
    centre = np.stack([c.center for c in cams]).mean(0)
    device = device or str(trainer.device)
    volume = make_volume(settings, centre, scene.camera_extent(), device)
    kind = trainer.model.kind
    depth_name = depth_output(kind) if settings.depth is None else DEPTH_OUTPUTS[settings.depth]
    if depth_name == "median_depth" and kind != "surfels":
        raise ValueError("--depth median: only surfels have a median depth; 3D Gaussians mesh their expected depth")
    render_s = fuse_s = 0.0
    with torch.no_grad():
        for k, cam in enumerate(cams):
            t0 = time.perf_counter()
            out = trainer.render(_CameraView(cam, trainer.device), ("rgb", "alpha", depth_name))
            depth = getattr(out, depth_name)[..., 0]
            depth = torch.where(out.alpha[..., 0] >= settings.alpha_min, depth, torch.zeros_like(depth))
            depth, rgb = depth.cpu().numpy(), out.rgb.clamp(0, 1).cpu().numpy()
            t1 = time.perf_counter()
            volume.integrate(depth, cam.K, cam.viewmat, rgb)
            t2 = time.perf_counter()
            render_s, fuse_s = render_s + t1 - t0, fuse_s + t2 - t1
            if report and (k + 1 == len(cams) or (k + 1) % max(1, len(cams) // 10) == 0):
                report(f"fused {k + 1}/{len(cams)} views ({volume.num_blocks} blocks)")
    settings.timings.update(render_s=render_s, fusion_s=fuse_s, views=len(cams), blocks=volume.num_blocks,
                            voxel=volume.voxel_grid * volume.bound.radius, trunc=volume.trunc,
                            radius=volume.bound.radius, depth=depth_name)
    return finish_mesh(volume, settings)
