"""Reading a fused sparse TSDF volume (kernels/tsdf.py) back out, Warp only: the cells marching cubes needs
(those whose 8 corners were all observed and straddle the zero level) with their corner values, and the colour
and world position of the surface vertices marching cubes returns."""
from __future__ import annotations

import warp as wp

from warpgs.kernels.tsdf import (BLOCK, BLOCK_OFFSET, BLOCK_VOXELS, grid_to_world, hash_find, pack_block,
                                 unpack_block)

vec8 = wp.types.vector(length=8, dtype=float)


@wp.func
def voxel_index(keys: wp.array(dtype=wp.int64), block_of_slot: wp.array(dtype=wp.int32), g: wp.vec3i) -> int:
    """Pool index of lattice point g, or -1 when its block was never allocated."""
    b = wp.vec3i(g[0] // BLOCK, g[1] // BLOCK, g[2] // BLOCK)
    slot = hash_find(keys, pack_block(b))
    if slot < 0:
        return -1
    blk = block_of_slot[slot]
    if blk < 0:
        return -1
    loc = g - b * BLOCK
    return blk * BLOCK_VOXELS + (loc[0] * BLOCK + loc[1]) * BLOCK + loc[2]


@wp.kernel
def surface_cells(block_key: wp.array(dtype=wp.int64), keys: wp.array(dtype=wp.int64),
                  block_of_slot: wp.array(dtype=wp.int32), tsdf: wp.array(dtype=float),
                  weight: wp.array(dtype=float), min_weight: float, corner_offsets: wp.array(dtype=wp.vec3i),
                  write: int, count: wp.array(dtype=wp.int32), cells: wp.array(dtype=wp.vec3i),
                  values: wp.array(dtype=float)):
    """One thread per pool voxel, the cell whose lowest corner it is. write=0 only counts the cells (the host
    then sizes `cells` [count] and `values` [8 count] and runs again with write=1). Cell subscripts are the
    lattice coordinates without the block offset, so cell (i, j, k) spans grid [i, i+1] * voxel."""
    tid = wp.tid()
    local = tid % BLOCK_VOXELS
    g = unpack_block(block_key[tid // BLOCK_VOXELS]) * BLOCK + wp.vec3i(
        local // (BLOCK * BLOCK), (local // BLOCK) % BLOCK, local % BLOCK)
    vals = vec8()
    lo = float(1.0e9)
    hi = float(-1.0e9)
    for c in range(8):
        i = voxel_index(keys, block_of_slot, g + corner_offsets[c])
        if i < 0:
            return
        if weight[i] < min_weight:
            return
        v = tsdf[i]
        vals[c] = v
        lo = wp.min(lo, v)
        hi = wp.max(hi, v)
    if not (lo < 0.0 and hi >= 0.0):
        return
    k = wp.atomic_add(count, 0, 1)
    if write != 0:
        o = BLOCK_OFFSET * BLOCK
        cells[k] = g - wp.vec3i(o, o, o)
        for c in range(8):
            values[k * 8 + c] = vals[c]


@wp.kernel
def shade_vertices(verts: wp.array(dtype=wp.vec3), keys: wp.array(dtype=wp.int64),
                   block_of_slot: wp.array(dtype=wp.int32), weight: wp.array(dtype=float),
                   voxel_color: wp.array(dtype=wp.vec3), voxel: float, centre: wp.vec3, radius: float,
                   contract: int, world: wp.array(dtype=wp.vec3), color: wp.array(dtype=wp.vec3)):
    """Grid-space vertex -> its world position and its colour, trilinear over the observed neighbours."""
    i = wp.tid()
    x = verts[i]
    q = x / voxel
    f = wp.vec3(wp.floor(q[0]), wp.floor(q[1]), wp.floor(q[2]))
    o = BLOCK_OFFSET * BLOCK
    g0 = wp.vec3i(int(f[0]) + o, int(f[1]) + o, int(f[2]) + o)
    t = q - f
    acc = wp.vec3()
    total = float(0.0)
    for c in range(8):
        dx = c & 1
        dy = (c >> 1) & 1
        dz = (c >> 2) & 1
        j = voxel_index(keys, block_of_slot, g0 + wp.vec3i(dx, dy, dz))
        if j >= 0:
            if weight[j] > 0.0:
                w = (wp.where(dx == 1, t[0], 1.0 - t[0]) * wp.where(dy == 1, t[1], 1.0 - t[1])
                     * wp.where(dz == 1, t[2], 1.0 - t[2]))
                acc = acc + voxel_color[j] * w
                total = total + w
    color[i] = wp.where(total > 1.0e-8, acc / wp.max(total, 1.0e-8), wp.vec3(0.5, 0.5, 0.5))
    world[i] = grid_to_world(x, centre, radius, contract)
