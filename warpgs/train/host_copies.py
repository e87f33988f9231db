"""Host copies of device tensors in reusable buffers, taken without stalling the GPU.

A `train.steps=auto` run copies its whole model with the Adam moments to host memory at every new best validation
score (train/best_state.py); on a large capture that is every 500 steps. Copied into fresh pageable memory, 708 MB
(a million primitives) took 0.53 s on an H200, the GPU idle meanwhile; into page-locked buffers, enqueued without a
host sync, 0.013 s (benchmarks/best_state_copy.py, best_state_copy_cuda_h200.json). The buffers are kept and grown
by a quarter beyond the need, so a model that densifies does not allocate at every copy. Tensors not on a CUDA device are copied synchronously
into the same kind of buffers (unpinned)."""
from __future__ import annotations

from typing import Dict, Hashable

import torch

GROWTH = 1.25  # a buffer that is too small is replaced by one this much larger than the need


class HostCopies:
    """copy(key, tensor) -> a host tensor holding tensor's values (a view of the key's buffer; valid until the
    next copy under that key). Copies from a CUDA device may still be in flight: call wait() before the host reads
    them (the device's own later work is ordered after them on its stream)."""

    def __init__(self):
        self._buffers: Dict[Hashable, torch.Tensor] = {}
        self._pending = set()  # CUDA devices with copies not yet waited for

    def copy(self, key: Hashable, tensor: torch.Tensor) -> torch.Tensor:
        tensor = tensor.detach()
        on_cuda = tensor.device.type == "cuda"
        buf = self._buffers.get(key)
        if buf is None or buf.dtype != tensor.dtype or buf.numel() < tensor.numel() or buf.is_pinned() != on_cuda:
            buf = self._allocate(tensor, on_cuda)
            self._buffers[key] = buf
        out = buf[:tensor.numel()].view(tensor.shape)
        out.copy_(tensor, non_blocking=on_cuda and buf.is_pinned())
        if on_cuda:
            self._pending.add(tensor.device)
        return out

    def wait(self) -> None:
        """Block until every copy taken so far has landed in host memory."""
        for device in self._pending:
            torch.cuda.synchronize(device)
        self._pending.clear()

    def nbytes(self) -> int:
        return sum(b.numel() * b.element_size() for b in self._buffers.values())

    @staticmethod
    def _allocate(tensor: torch.Tensor, on_cuda: bool) -> torch.Tensor:
        size = max(1, int(tensor.numel() * GROWTH))
        if on_cuda:
            try:
                return torch.empty(size, dtype=tensor.dtype, pin_memory=True)
            except RuntimeError:  # page-locked memory refused: a plain buffer (the copy then waits for the GPU)
                pass
        return torch.empty(size, dtype=tensor.dtype)
