"""The deterministic blend adjoint's host side (raster option `deterministic`): the GPU adjoint writes each summing
group's per-pair sums to slots of a zeroed workspace block instead of adding them to the primitives with atomics,
then kernels/pair_sums.sum_pair_parts adds every primitive's slots in a fixed order (that file says which).
Same sums as the default path up to float32 rounding, and the same bits on every run.

Costs over the default: one int per tile pair and two ints per primitive kept from the forward, and a float block
of pairs x groups-per-tile x gradient floats (10 + C for 3D Gaussians, 19 + C for surfels) zeroed and read once
per backward. The CPU's per-thread kernels need none of this: they are deterministic already."""
from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from warpgs.kernels import pair_sums
from warpgs.render.defaults import PER_WARP_ADJOINTS
from warpgs.render.workspace import Workspace


@dataclass
class PairOrder:
    """What the forward keeps for a deterministic backward (tile_binning.pair_order)."""
    total: int  # tile pairs
    positions: wp.array  # [total]: emitted slot -> sorted position
    ranges: wp.array  # [N] vec2i: each primitive's (first emitted slot, number of pairs)


def choose_kernel(kernels, tile_size: int, variant: str, block: int, num_features: int, absgrad: bool = False):
    """(kernel, block_dim, parts): the deterministic twin of the GPU adjoint `variant` of kernels (blend_gpu or
    surfel_blend_gpu), and how many summing groups each tile has. block: the "block" variant's block size.
    absgrad: the 3D per-warp kernel that also sums |d means2d| (blend_gpu only)."""
    per_tile = tile_size * tile_size
    if variant in PER_WARP_ADJOINTS and per_tile % kernels.WARP == 0:  # scatter: lane 0's sums here
        block = min(per_tile, 256)
        extra = (True,) if absgrad else ()
        return kernels.backward_kernel_warp_sums(block, num_features, True, *extra), block, per_tile // kernels.WARP
    return kernels.backward_kernel(block, True, num_features, True), block, per_tile // block


def run_pair_adjoint(ws: Workspace, key: str, fields, n: int, pairs: PairOrder, parts: int, caller: dict,
                     num_tiles: int, launch) -> list:
    """Runs the deterministic adjoint (one launch over all tiles) and sums its slots per primitive. fields: the
    kernel's gradient targets in argument order, (name, floats per primitive, dtype) for a sum returned in a zeroed
    workspace block, or a key of `caller`: (the caller's zeroed [N] array, or a dummy the kernel leaves alone, and
    whether it is used). launch(key, first_tile, tile_count, targets) makes the launch. Returns the workspace sums
    (valid until the next backward on it)."""
    slots = pairs.total * parts
    plan = []  # (label, floats per primitive, dtype, the caller's array or None)
    for f in fields:
        if isinstance(f, str):
            a, used = caller[f]
            if used and a.shape[0] != n:
                raise ValueError(f"{key}: the {f} gradient has {a.shape[0]} rows for {n} primitives")
            plan.append((f, wp.types.type_size_in_bytes(a.dtype) // 4 if used else 0, a.dtype, a))
        else:
            plan.append((f[0], f[1], f[2], None))
    widest = max(p[1] for p in plan)
    if slots * widest >= 2**31:  # the kernels index each gradient's slots with 32-bit ints
        raise ValueError(f"deterministic render: {pairs.total} tile pairs x {parts} parts per tile x {widest} floats "
                         f"is past 2^31 (int32 indices); use a smaller tile_size, fewer primitives or pixels, or "
                         f"deterministic=False")
    own = [p for p, f in zip(plan, fields) if not isinstance(f, str)]
    sums = ws.array("grad_projected", sum(p[1] for p in own) * n, float)
    sums.zero_()
    per_slot = ws.array(f"{key}_pair_slots", sum(p[1] for p in plan) * slots, float)
    per_slot.zero_()  # groups that blended nothing of a pair leave its slot alone

    targets, jobs, slot_at, sum_at = [], [], 0, 0
    for (label, floats, dtype, dest), f in zip(plan, fields):
        if isinstance(f, str) and floats == 0:  # no features: the kernel gets the caller's dummy
            targets.append(dest)
            continue
        targets.append(ws.view(f"{key}_slots_{label}", per_slot, slot_at, slots, dtype))
        src = ws.view(f"{key}_slots_flat_{label}", per_slot, slot_at, slots * floats, float)
        if dest is None:
            dest_flat = ws.view(f"{key}_sum_{label}", sums, sum_at, n * floats, float)
            sum_at += n * floats
        else:
            dest_flat = ws.view(f"{key}_caller_flat_{label}", dest, 0, n * floats, float)
        jobs.append((label, floats, src, dest_flat))
        slot_at += slots * floats
    launch((key, "pairs"), 0, num_tiles, targets)
    for label, floats, src, dest_flat in jobs:
        ws.launches.launch((key, "pair_sums", label), pair_sums.sum_pair_parts, dest_flat.shape[0],
                           [pairs.positions, pairs.ranges, parts, floats, src, dest_flat])
    at, out = 0, []
    for label, floats, dtype, dest in own:
        out.append(ws.view(f"{key}_sum_typed_{label}", sums, at, n, dtype))
        at += n * floats
    return out
