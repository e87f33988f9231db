"""Differentiable all-to-all of row blocks whose sizes differ between ranks: rank r sends sends[j] to rank j and
receives one block from every rank; the backward pass sends each received block's gradient back to its sender.
The block sizes go first (a small all-to-all), then every block travels at its own size in one uneven
all_to_all_single (gloo and NCCL both take split sizes), so no rank sends padding."""
from __future__ import annotations

from typing import List, Optional, Sequence

import torch
import torch.distributed as dist

from warpgs.render.differentiable_once import differentiable_once


def _all_to_all_rows(sends: Sequence[torch.Tensor], group) -> List[torch.Tensor]:
    world = dist.get_world_size(group)
    if len(sends) != world:
        raise ValueError(f"sends: expected one block per rank ({world}), got {len(sends)}")
    columns = sends[0].shape[1]
    if any(s.dim() != 2 or s.shape[1] != columns for s in sends):
        raise ValueError(f"sends: every block must be [rows, {columns}], got {[tuple(s.shape) for s in sends]}")
    device = sends[0].device
    counts = torch.tensor([s.shape[0] for s in sends], dtype=torch.int64, device=device)
    received_counts = torch.empty_like(counts)
    dist.all_to_all_single(received_counts, counts, group=group)
    out_sizes, in_sizes = received_counts.tolist(), counts.tolist()
    outgoing = torch.cat([s.contiguous() for s in sends])
    incoming = outgoing.new_empty((sum(out_sizes), columns))
    dist.all_to_all_single(incoming, outgoing, output_split_sizes=out_sizes, input_split_sizes=in_sizes,
                           group=group)
    return list(incoming.split(out_sizes))


class _ExchangeRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, group, *sends):
        ctx.group, ctx.device, ctx.dtype = group, sends[0].device, sends[0].dtype
        received = _all_to_all_rows(sends, group)
        ctx.received_shapes = [tuple(r.shape) for r in received]
        return tuple(received)

    @staticmethod
    @differentiable_once("the row exchange (exchange_rows)")
    def backward(ctx, *grads):
        filled = [g.contiguous() if g is not None else torch.zeros(shape, dtype=ctx.dtype, device=ctx.device)
                  for g, shape in zip(grads, ctx.received_shapes)]
        returned = _all_to_all_rows(filled, ctx.group)
        return (None,) + tuple(returned)


def exchange_rows(sends: Sequence[torch.Tensor], group: Optional[dist.ProcessGroup] = None) -> List[torch.Tensor]:
    """Block sends[j] ([n_j, C], same C and dtype everywhere) goes to rank j; returns the block each rank sent here,
    in rank order. Differentiable: gradients of the returned blocks flow back to the senders' blocks."""
    return list(_ExchangeRows.apply(group, *sends))
