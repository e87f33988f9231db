"""The render of no primitives, for both render ops: the Warp pipelines want at least one primitive, and a blend of
nothing is known without them (every pixel keeps transmittance 1: colour, alpha, depth and the rest are 0)."""
from __future__ import annotations

import torch


class EmptySceneFunction(torch.autograd.Function):
    """apply(shapes, *inputs) -> one zero tensor per shape (on the first input's device), connected to the inputs
    (None allowed) so that a loss on them backpropagates as on any render: a zero gradient for every input."""

    @staticmethod
    def forward(ctx, shapes, *inputs):
        ctx.meta = [None if t is None else (t.shape, t.dtype, t.device) for t in inputs]
        return tuple(inputs[0].new_zeros(shape) for shape in shapes)

    @staticmethod
    def backward(ctx, *_grads):
        return (None,) + tuple(torch.zeros(meta[0], dtype=meta[1], device=meta[2]) if need else None
                               for meta, need in zip(ctx.meta, ctx.needs_input_grad[1:]))
