"""The input gradients of a render op's backward as contiguous parts of one zeroed block."""
from __future__ import annotations

import functools
import math

OPACITIES, FEATURES = 3, 5  # the parts the blend adjoint always writes (the op's inputs: means, quats, scales,
# opacities, coeffs, features, viewmat, intrinsics)


class GradientBlock:
    """The op's eight input gradients, zeros where `needs` (and for opacities and features always: the blend adjoint
    writes them), as contiguous parts of one block: on a GPU one allocation and one fill instead of one of each per
    input. The blend adjoint's two parts are reachable by address (`address`) before any torch view exists, so a
    backward can launch its blend adjoint first and make the views (a dispatch each) while the GPU runs it.
    saved: the op's saved (means, quats, scales, opacities, coeffs, features, ...); camera_shapes: viewmat's and
    intrinsics' shapes as the caller gave them."""

    def __init__(self, saved, camera_shapes, needs):
        self.needs = needs
        self.shapes = [tuple(t.shape) for t in saved[:6]] + [tuple(s) for s in camera_shapes]
        self.taken = [need or i in (OPACITIES, FEATURES) for i, need in enumerate(needs)]
        sizes = [math.prod(shape) if take else 0 for shape, take in zip(self.shapes, self.taken)]
        self.offsets = [sum(sizes[:i]) for i in range(len(sizes))]
        self.block = saved[0].new_zeros(sum(sizes))

    def address(self, part: int) -> int:
        """The device address of a part (float32 elements)."""
        return self.block.data_ptr() + 4 * self.offsets[part]

    def views(self):
        """(grads, opacity gradient, feature gradient): the eight gradients as the backward returns them (None where
        not needed) and the two parts the blend adjoint writes."""
        views = [self.block.as_strided(shape, _contiguous_strides(shape), offset) if take else None
                 for shape, offset, take in zip(self.shapes, self.offsets, self.taken)]
        grads = [v if need else None for v, need in zip(views, self.needs)]
        return grads, views[OPACITIES], views[FEATURES]


@functools.lru_cache(maxsize=256)  # a handful of shapes per model; saves a loop per gradient per backward
def _contiguous_strides(shape) -> tuple:
    strides, step = [], 1
    for d in reversed(shape):
        strides.append(step)
        step *= max(d, 1)
    return tuple(reversed(strides))
