"""A sparse TSDF volume on the CPU or a CUDA device: fuse depth maps into it, extract a triangle mesh.

Host side of kernels/tsdf.py and kernels/tsdf_extract.py: it owns the hash table and the voxel pool and grows
them as frames add blocks (see kernels/tsdf.py for the layout). Inputs are numpy arrays; Warp arrays live on
`device`. Marching cubes is Warp's `sparse_marching_cubes_from_cells` over the cells that straddle the surface.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import warp as wp

from warpgs.kernels import tsdf as K
from warpgs.kernels import tsdf_extract as X


@dataclass
class Bound:
    """The part of the world the volume covers: the cube of half-size `radius` around `centre`, or with
    `contract` the whole world, squeezed (outside the ball of `radius`) into the cube of half-size 2 radius."""
    centre: np.ndarray
    radius: float
    contract: bool = False

    def __post_init__(self):
        self.centre = np.asarray(self.centre, dtype=np.float64).reshape(3)
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"bound radius: expected a positive number, got {self.radius}")


@dataclass
class Mesh:
    vertices: np.ndarray  # [V, 3] float32 world
    faces: np.ndarray  # [F, 3] int32, counter-clockwise seen from the side the depth maps saw
    colors: np.ndarray  # [V, 3] float32 in [0, 1]


def _pose_parts(viewmat: np.ndarray):
    """world-to-camera 4x4 -> (world-to-cam rotation, its translation, camera-to-world rotation, centre)."""
    R = np.asarray(viewmat, dtype=np.float64)[:3, :3]
    t = np.asarray(viewmat, dtype=np.float64)[:3, 3]
    return R, t, R.T, -R.T @ t


class SparseTSDFVolume:
    """voxel and trunc are world lengths (at the centre, for a contracted bound); depth outside
    (depth_min, depth_max) is ignored. Voxel weights are capped at max_weight (a running mean of the latest)."""

    def __init__(self, bound: Bound, voxel: float, trunc: float, depth_min: float = 1e-3,
                 depth_max: float = np.inf, device: str = "cpu", max_weight: float = 1e4,
                 initial_blocks: int = 1 << 14):
        for name, value in (("voxel", voxel), ("trunc", trunc)):
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name}: expected a positive length, got {value}")
        if not depth_max > depth_min:
            raise ValueError(f"depth range: expected depth_max > depth_min, got ({depth_min}, {depth_max})")
        self.bound, self.device = bound, wp.get_device(device)
        self.voxel_grid = float(voxel / bound.radius)  # the lattice step in grid units
        if 2.0 * (2.0 if bound.contract else 1.0) / (self.voxel_grid * K.BLOCK) >= K.BLOCK_OFFSET:
            raise ValueError(f"voxel: {voxel} is too small for a bound of radius {bound.radius}")
        self.trunc, self.depth_min = float(trunc), float(depth_min)
        self.depth_max = float(min(depth_max, 3.0e38))
        self.max_weight = float(max_weight)
        self.frames = 0
        self._counters = wp.zeros(2, dtype=wp.int32, device=self.device)
        self._pool_count = wp.zeros(1, dtype=wp.int32, device=self.device)
        self.num_blocks = 0
        self._alloc_table(_pow2(4 * initial_blocks))
        self._alloc_pool(initial_blocks)

    # ----- storage ------------------------------------------------------------------------------------------
    def _alloc_table(self, capacity: int) -> None:
        self.keys = wp.full(capacity, -1, dtype=wp.int64, device=self.device)
        self.block_of_slot = wp.full(capacity, -1, dtype=wp.int32, device=self.device)
        self.slot_frame = wp.full(capacity, -1, dtype=wp.int32, device=self.device)
        self.active = wp.zeros(capacity, dtype=wp.int32, device=self.device)

    def _alloc_pool(self, blocks: int) -> None:
        n = blocks * K.BLOCK_VOXELS
        self.block_key = wp.zeros(blocks, dtype=wp.int64, device=self.device)
        self.tsdf = wp.zeros(n, dtype=float, device=self.device)
        self.weight = wp.zeros(n, dtype=float, device=self.device)
        self.color = wp.zeros(n, dtype=wp.vec3, device=self.device)

    def _grow_pool(self, blocks: int) -> None:
        old = (self.block_key, self.tsdf, self.weight, self.color)
        self._alloc_pool(blocks)
        for new, prev in zip((self.block_key, self.tsdf, self.weight, self.color), old):
            wp.copy(new, prev, count=prev.shape[0])

    def _grow_table(self) -> None:
        """Twice the slots, every key moved over (the slots touched this frame are forgotten: the frame repeats)."""
        old_keys, old_blocks = self.keys, self.block_of_slot
        capacity = 2 * old_keys.shape[0]
        while True:
            self._alloc_table(capacity)
            self._counters.zero_()
            wp.launch(K.rehash_slots, dim=old_keys.shape[0],
                      inputs=[old_keys, old_blocks, self.keys, self.block_of_slot, self._counters], device=self.device)
            if int(self._counters.numpy()[1]) == 0:
                return
            capacity *= 2

    # ----- fusion -------------------------------------------------------------------------------------------
    def integrate(self, depth: np.ndarray, K_matrix: np.ndarray, viewmat: np.ndarray,
                  color: Optional[np.ndarray] = None) -> int:
        """Fuse one depth map (camera z per pixel, [H, W]; invalid: 0, negative, NaN or inf) with its colour
        ([H, W, 3] in [0, 1]). Returns the number of blocks this frame touched."""
        depth = np.asarray(depth, dtype=np.float32)
        if depth.ndim == 3 and depth.shape[-1] == 1:
            depth = depth[..., 0]
        if depth.ndim != 2:
            raise ValueError(f"depth: expected an [H, W] map, got shape {depth.shape}")
        H, W = depth.shape
        if color is None:
            color = np.full((H, W, 3), 0.5, dtype=np.float32)
        color = np.asarray(color, dtype=np.float32)
        if color.shape != (H, W, 3):
            raise ValueError(f"color: expected shape {(H, W, 3)} like the depth map, got {color.shape}")
        Km = np.asarray(K_matrix, dtype=np.float64)
        intr = wp.vec4(Km[0, 0], Km[1, 1], Km[0, 2], Km[1, 2])
        R, t, R_c2w, c = _pose_parts(viewmat)
        depth_wp = wp.array(depth.reshape(-1), dtype=float, device=self.device)
        color_wp = wp.array(color.reshape(-1, 3), dtype=wp.vec3, device=self.device)
        b = self.bound
        common = dict(centre=wp.vec3(*b.centre), contract=int(b.contract), voxel=self.voxel_grid)
        frame = self.frames
        while True:
            if 2 * self.num_blocks > self.keys.shape[0]:  # keep the table at most half full
                self._grow_table()
            self._counters.zero_()
            wp.launch(K.allocate_blocks, dim=H * W, device=self.device, inputs=[
                depth_wp, W, intr, wp.mat33(*R_c2w.reshape(-1)), wp.vec3(*c), common["centre"],
                1.0 / b.radius, common["contract"], 2.0 if b.contract else 1.0, self.voxel_grid, self.trunc,
                self.depth_min, self.depth_max, frame, self.keys, self.slot_frame, self.active, self._counters])
            n_active, overflow = (int(v) for v in self._counters.numpy())
            if not overflow:
                break
            self._grow_table()
        self.frames += 1
        if n_active == 0:
            return 0
        if self.num_blocks + n_active > self.block_key.shape[0]:
            self._grow_pool(max(2 * self.block_key.shape[0], self.num_blocks + n_active))
        wp.launch(K.assign_blocks, dim=n_active, device=self.device,
                  inputs=[self.active, self.keys, self.block_of_slot, self.block_key, self._pool_count])
        self.num_blocks = int(self._pool_count.numpy()[0])
        wp.launch(K.integrate_blocks, dim=n_active * K.BLOCK_VOXELS, device=self.device, inputs=[
            self.active, self.keys, self.block_of_slot, depth_wp, color_wp, W, H, intr, wp.mat33(*R.reshape(-1)),
            wp.vec3(*t), common["centre"], b.radius, common["contract"], self.voxel_grid, self.trunc,
            self.depth_min, self.depth_max, self.max_weight, self.tsdf, self.weight, self.color])
        return n_active

    # ----- extraction ---------------------------------------------------------------------------------------
    def extract_mesh(self, min_weight: float = 1.0) -> Mesh:
        """Marching cubes over the cells whose corners all have weight >= min_weight."""
        import warp.geometry as wg

        n_voxels = self.num_blocks * K.BLOCK_VOXELS
        if n_voxels == 0:
            return _empty_mesh()
        offsets = wp.array(np.asarray(wg.IsoSurfaceMarchingCubes.CUBE_CORNER_OFFSETS, dtype=np.int32),
                           dtype=wp.vec3i, device=self.device)
        count = wp.zeros(1, dtype=wp.int32, device=self.device)
        cells = wp.zeros(1, dtype=wp.vec3i, device=self.device)
        values = wp.zeros(8, dtype=float, device=self.device)
        args = [self.block_key, self.keys, self.block_of_slot, self.tsdf, self.weight, float(min_weight), offsets]
        wp.launch(X.surface_cells, dim=n_voxels, inputs=args + [0, count, cells, values], device=self.device)
        n_cells = int(count.numpy()[0])
        if n_cells == 0:
            return _empty_mesh()
        count.zero_()
        cells = wp.zeros(n_cells, dtype=wp.vec3i, device=self.device)
        values = wp.zeros(8 * n_cells, dtype=float, device=self.device)
        wp.launch(X.surface_cells, dim=n_voxels, inputs=args + [1, count, cells, values], device=self.device)
        verts, indices = wg.sparse_marching_cubes_from_cells(cells, values, origin=(0.0, 0.0, 0.0),
                                                             cell_width=self.voxel_grid, threshold=0.0,
                                                             device=self.device)
        n_verts = verts.shape[0]
        if n_verts == 0:
            return _empty_mesh()
        world = wp.zeros(n_verts, dtype=wp.vec3, device=self.device)
        color = wp.zeros(n_verts, dtype=wp.vec3, device=self.device)
        b = self.bound
        wp.launch(X.shade_vertices, dim=n_verts, device=self.device, inputs=[
            verts, self.keys, self.block_of_slot, self.weight, self.color, self.voxel_grid, wp.vec3(*b.centre),
            b.radius, int(b.contract), world, color])
        return Mesh(world.numpy().astype(np.float32), indices.numpy().reshape(-1, 3).astype(np.int32),
                    np.clip(color.numpy(), 0.0, 1.0).astype(np.float32))


def _pow2(n: int) -> int:
    return 1 << max(4, int(n - 1).bit_length())


def _empty_mesh() -> Mesh:
    return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32))
