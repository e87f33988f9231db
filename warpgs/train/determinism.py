"""train.deterministic: what the trainer switches on so that two runs of one config give the same bits on GPUs too.

The renders take `deterministic=True` (the trainer passes it: fixed-order sums in the blend adjoint instead of float
atomics, render/pair_adjoint.py). This module does the torch side: `torch.use_deterministic_algorithms(True)`, which
makes torch pick deterministic CUDA kernels (index_add_, scatter_add_, ...) and raise an error naming any op that has
none, instead of silently varying. It is process-wide and stays on after the trainer is done.
"""
import os

import torch


def use_deterministic_algorithms(device: torch.device, model_parallel: bool) -> None:
    """Torch's deterministic mode for a train.deterministic run on `device`. train.parallel=model renders through
    the splat exchange (render/splats.py), whose adjoint still adds with atomics: refused rather than half kept."""
    if model_parallel:
        raise ValueError("train.deterministic: not available with train.parallel=model yet (its splat renderer's "
                         "adjoint adds with float atomics); use train.parallel=data or turn it off")
    if device.type == "cuda":
        # cuBLAS: a fixed workspace (torch releases before late 2025 raise without it; read when the first cuBLAS
        # handle is made, so a process that already used cuBLAS keeps its own). cuDNN: no benchmarking, which can
        # pick another (deterministic) algorithm, and so other bits, on another run.
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.backends.cudnn.benchmark = False
    torch.use_deterministic_algorithms(True, warn_only=False)
