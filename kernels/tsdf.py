"""TSDF fusion into a sparse volume of voxel blocks (Warp only, CPU and CUDA).

The volume lives in "grid space": world points are centred on `centre` and divided by `radius`, and with
`contract` set the outside of the unit ball is squeezed into the ball of radius 2 (the mip-NeRF 360 map), so
an unbounded capture's background fits a finite grid. Lattice point g (int, with BLOCK_OFFSET*BLOCK added to
every coordinate so all of them are non-negative) sits at grid position (g - BLOCK_OFFSET*BLOCK) * voxel.

Blocks of BLOCK^3 lattice points are allocated only where depth samples fall: a hash table with open addressing
(`keys`, int64 packed block coordinates, EMPTY where free) maps a block to its slot, and `block_of_slot` maps the
slot to the block's place in the voxel pool (tsdf, weight, colour: BLOCK_VOXELS entries per block). Per frame:
`allocate_blocks` inserts the blocks within the truncation band of every depth pixel and lists the slots it
touched (`active`), the host grows the pool, `assign_blocks` gives new slots their pool block, and
`integrate_blocks` updates the voxels of the touched blocks only (each voxel by one thread: no atomics).
The stored value is the projective signed distance (depth - camera z, positive in front of the surface) divided
by the truncation distance and clamped to [-1, 1]; voxels more than one truncation behind the surface are left
alone.
"""
from __future__ import annotations

import warp as wp

BLOCK = 8
BLOCK_VOXELS = BLOCK * BLOCK * BLOCK
BLOCK_OFFSET = 1 << 19  # added to block coordinates so they pack as non-negative 21-bit fields
EMPTY = wp.constant(wp.int64(-1))
MAX_PROBES = 128  # a longer probe sequence reports overflow: the host grows the table and repeats the frame
MAX_BAND_SAMPLES = 64


@wp.func
def pack_block(b: wp.vec3i) -> wp.int64:
    return (wp.int64(b[0]) << wp.int64(42)) | (wp.int64(b[1]) << wp.int64(21)) | wp.int64(b[2])


@wp.func
def unpack_block(key: wp.int64) -> wp.vec3i:
    m = wp.int64(0x1FFFFF)
    return wp.vec3i(int((key >> wp.int64(42)) & m), int((key >> wp.int64(21)) & m), int(key & m))


@wp.func
def hash_slot(key: wp.int64, mask: wp.int64) -> int:
    # a multiplicative mix of the packed key (wraps on overflow), so neighbouring blocks spread over the table
    h = key * wp.int64(-7046029254386353131)
    h = h ^ (h >> wp.int64(29))
    return int(h & mask)


@wp.func
def hash_insert(keys: wp.array(dtype=wp.int64), key: wp.int64) -> int:
    """The slot holding `key`, inserting it if absent; -1 when MAX_PROBES slots were taken by other keys."""
    mask = wp.int64(keys.shape[0] - 1)
    slot = hash_slot(key, mask)
    for _probe in range(MAX_PROBES):
        prev = wp.atomic_cas(keys, slot, EMPTY, key)
        if prev == EMPTY or prev == key:
            return slot
        slot = (slot + 1) & int(mask)
    return -1


@wp.func
def hash_find(keys: wp.array(dtype=wp.int64), key: wp.int64) -> int:
    """The slot holding `key`, or -1."""
    mask = wp.int64(keys.shape[0] - 1)
    slot = hash_slot(key, mask)
    for _probe in range(MAX_PROBES):
        k = keys[slot]
        if k == key:
            return slot
        if k == EMPTY:
            return -1
        slot = (slot + 1) & int(mask)
    return -1


@wp.func
def contract_point(x: wp.vec3, contract: int) -> wp.vec3:
    if contract != 0:
        n = wp.length(x)
        if n > 1.0:
            return x * ((2.0 - 1.0 / n) / n)
    return x


@wp.func
def uncontract_point(x: wp.vec3, contract: int) -> wp.vec3:
    if contract != 0:
        n = wp.length(x)
        if n > 1.0:
            m = wp.min(n, 1.999)  # the sphere of radius 2 is infinity; stop just short of it
            return x * ((1.0 / (2.0 - m)) / n)
    return x


@wp.func
def world_to_grid(p: wp.vec3, centre: wp.vec3, inv_radius: float, contract: int) -> wp.vec3:
    return contract_point((p - centre) * inv_radius, contract)


@wp.func
def grid_to_world(x: wp.vec3, centre: wp.vec3, radius: float, contract: int) -> wp.vec3:
    return centre + uncontract_point(x, contract) * radius


@wp.func
def stretch(x: wp.vec3, contract: int) -> float:
    """How much larger a grid step is in the world at grid point x than in the uncontracted centre (radially
    1/(2-|x|)^2): the truncation distance grows by it so it stays a few voxels wide in the background."""
    if contract != 0:
        n = wp.length(x)
        if n > 1.0:
            r = 1.0 / (2.0 - wp.min(n, 1.999))
            return r * r
    return 1.0


@wp.func
def block_of_point(x: wp.vec3, voxel: float) -> wp.vec3i:
    s = 1.0 / (voxel * float(BLOCK))
    return wp.vec3i(int(wp.floor(x[0] * s)) + BLOCK_OFFSET, int(wp.floor(x[1] * s)) + BLOCK_OFFSET,
                    int(wp.floor(x[2] * s)) + BLOCK_OFFSET)


@wp.func
def lattice_position(g: wp.vec3i, voxel: float) -> wp.vec3:
    o = BLOCK_OFFSET * BLOCK
    return wp.vec3(float(g[0] - o), float(g[1] - o), float(g[2] - o)) * voxel


@wp.func
def inside_bound(x: wp.vec3, bound: float) -> bool:
    return wp.abs(x[0]) <= bound and wp.abs(x[1]) <= bound and wp.abs(x[2]) <= bound


@wp.kernel
def allocate_blocks(depth: wp.array(dtype=float), width: int, intrinsics: wp.vec4, cam_to_world: wp.mat33,
                    cam_centre: wp.vec3, centre: wp.vec3, inv_radius: float, contract: int, bound: float,
                    voxel: float, trunc: float, depth_min: float, depth_max: float, frame: int,
                    keys: wp.array(dtype=wp.int64), slot_frame: wp.array(dtype=wp.int32),
                    active: wp.array(dtype=wp.int32), counters: wp.array(dtype=wp.int32)):
    """One thread per pixel: every block the pixel's truncation band [d - t, d + t] (camera z) passes through.
    counters[0]: slots touched this frame (listed in active), counters[1]: set on hash-table overflow."""
    pix = wp.tid()
    d = depth[pix]
    if not (d > depth_min and d < depth_max):  # also skips NaN
        return
    u = float(pix % width) + 0.5
    v = float(pix // width) + 0.5
    ray = cam_to_world @ wp.vec3((u - intrinsics[2]) / intrinsics[0], (v - intrinsics[3]) / intrinsics[1], 1.0)
    surface = world_to_grid(cam_centre + ray * d, centre, inv_radius, contract)
    t = trunc * stretch(surface, contract)
    # steps of half a block in the grid, measured where the band is (the stretch is about constant across it)
    step_world = 0.5 * float(BLOCK) * voxel / inv_radius * stretch(surface, contract) / wp.length(ray)
    n = wp.min(int(2.0 * t / step_world) + 2, MAX_BAND_SAMPLES)
    for k in range(n):
        z = d - t + 2.0 * t * float(k) / float(n - 1)
        if z <= depth_min:
            continue
        x = world_to_grid(cam_centre + ray * z, centre, inv_radius, contract)
        if not inside_bound(x, bound):
            continue
        slot = hash_insert(keys, pack_block(block_of_point(x, voxel)))
        if slot < 0:
            counters[1] = 1
            return
        if wp.atomic_exch(slot_frame, slot, frame) != frame:
            active[wp.atomic_add(counters, 0, 1)] = slot


@wp.kernel
def assign_blocks(active: wp.array(dtype=wp.int32), keys: wp.array(dtype=wp.int64),
                  block_of_slot: wp.array(dtype=wp.int32), block_key: wp.array(dtype=wp.int64),
                  pool_count: wp.array(dtype=wp.int32)):
    """New slots of this frame get the next free pool block (every slot is listed once per frame)."""
    slot = active[wp.tid()]
    if block_of_slot[slot] < 0:
        b = wp.atomic_add(pool_count, 0, 1)
        block_of_slot[slot] = b
        block_key[b] = keys[slot]


@wp.func
def bilinear_depth(depth: wp.array(dtype=float), width: int, height: int, u: float, v: float, nearest: float,
                   depth_min: float, depth_max: float, max_step: float) -> float:
    """Depth at image point (u, v) interpolated between the 4 nearest pixel centres, when all 4 are valid and
    within max_step + 5% of each other (one surface); else the nearest pixel's. Nearest alone puts a slanted surface
    up to half a pixel's depth change off."""
    x = u - 0.5
    y = v - 0.5
    c0 = int(wp.floor(x))
    r0 = int(wp.floor(y))
    if c0 < 0 or r0 < 0 or c0 + 1 >= width or r0 + 1 >= height:
        return nearest
    a = depth[r0 * width + c0]
    b = depth[r0 * width + c0 + 1]
    c = depth[(r0 + 1) * width + c0]
    e = depth[(r0 + 1) * width + c0 + 1]
    lo = wp.min(wp.min(a, b), wp.min(c, e))
    hi = wp.max(wp.max(a, b), wp.max(c, e))
    # one surface: the spread is what a slanted plane makes (a few % of the depth), or within the band
    if not (lo > depth_min and hi < depth_max and hi - lo <= max_step + 0.05 * lo):
        return nearest
    fx = x - float(c0)
    fy = y - float(r0)
    # in inverse depth, which is affine in (u, v) across a plane: exact for planar pieces
    inv = ((1.0 / a) * (1.0 - fx) + (1.0 / b) * fx) * (1.0 - fy) + ((1.0 / c) * (1.0 - fx) + (1.0 / e) * fx) * fy
    return 1.0 / inv


@wp.kernel
def integrate_blocks(active: wp.array(dtype=wp.int32), keys: wp.array(dtype=wp.int64),
                     block_of_slot: wp.array(dtype=wp.int32), depth: wp.array(dtype=float),
                     color: wp.array(dtype=wp.vec3), width: int, height: int, intrinsics: wp.vec4,
                     world_to_cam: wp.mat33, world_to_cam_t: wp.vec3, centre: wp.vec3, radius: float,
                     contract: int, voxel: float, trunc: float, depth_min: float, depth_max: float,
                     max_weight: float, tsdf: wp.array(dtype=float), weight: wp.array(dtype=float),
                     voxel_color: wp.array(dtype=wp.vec3)):
    """One thread per voxel of a touched block: project it, read the depth there (bilinear) and fold the
    truncated signed distance and the pixel's colour into the running weighted means."""
    tid = wp.tid()
    slot = active[tid // BLOCK_VOXELS]
    local = tid % BLOCK_VOXELS
    b = unpack_block(keys[slot])
    g = b * BLOCK + wp.vec3i(local // (BLOCK * BLOCK), (local // BLOCK) % BLOCK, local % BLOCK)
    x = lattice_position(g, voxel)
    p = world_to_cam @ grid_to_world(x, centre, radius, contract) + world_to_cam_t
    if p[2] <= depth_min:
        return
    u = intrinsics[0] * p[0] / p[2] + intrinsics[2]
    v = intrinsics[1] * p[1] / p[2] + intrinsics[3]
    col = int(wp.floor(u))
    row = int(wp.floor(v))
    if col < 0 or row < 0 or col >= width or row >= height:
        return
    d = depth[row * width + col]
    if not (d > depth_min and d < depth_max):
        return
    t = trunc * stretch(x, contract)
    d = bilinear_depth(depth, width, height, u, v, d, depth_min, depth_max, 0.5 * t)
    sdf = d - p[2]
    if sdf < -t:
        return
    value = wp.min(sdf / t, 1.0)
    i = block_of_slot[slot] * BLOCK_VOXELS + local
    w = weight[i]
    w_new = w + 1.0
    tsdf[i] = (tsdf[i] * w + value) / w_new
    voxel_color[i] = (voxel_color[i] * w + color[row * width + col]) / w_new
    weight[i] = wp.min(w_new, max_weight)


@wp.kernel
def rehash_slots(old_keys: wp.array(dtype=wp.int64), old_block_of_slot: wp.array(dtype=wp.int32),
                 keys: wp.array(dtype=wp.int64), block_of_slot: wp.array(dtype=wp.int32),
                 counters: wp.array(dtype=wp.int32)):
    """Move every key of a table into a larger one (counters[1] set if even that one overflows)."""
    i = wp.tid()
    key = old_keys[i]
    if key == EMPTY:
        return
    slot = hash_insert(keys, key)
    if slot < 0:
        counters[1] = 1
        return
    block_of_slot[slot] = old_block_of_slot[i]
