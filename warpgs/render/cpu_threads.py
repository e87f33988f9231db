"""Spreading the per-pixel launches over CPU threads.

Warp runs a CPU launch on one thread but releases the GIL while it runs, so launching disjoint tile ranges
from a few Python threads uses every core. Work is split into more chunks than threads and dealt out
round-robin, since tiles differ a lot in cost. Torch-free.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, List, Optional, Sequence, Tuple

_pool: ThreadPoolExecutor | None = None


def cpu_threads() -> int:
    """WARPGS_CPU_THREADS, else the cores this process may use (at most 16)."""
    env = os.environ.get("WARPGS_CPU_THREADS")
    if env:
        return max(1, int(env))
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 1
    return max(1, min(16, cores))


def tile_ranges_per_thread(num_tiles: int, threads: int, chunks_per_thread: int = 4) -> List[List[Tuple[int, int]]]:
    """For each thread, its (first_tile, count) chunks."""
    chunks = max(1, min(num_tiles, threads * chunks_per_thread))
    bounds = [num_tiles * c // chunks for c in range(chunks + 1)]
    ranges = [(bounds[c], bounds[c + 1] - bounds[c]) for c in range(chunks) if bounds[c + 1] > bounds[c]]
    return [ranges[t::threads] for t in range(threads) if ranges[t::threads]]


def run_threads(work: Callable[[int, List[Tuple[int, int]]], None], per_thread: List[List[Tuple[int, int]]],
                kernels: Sequence = (), device=None, block_dim: Optional[int] = None) -> None:
    """Calls work(thread_index, chunks) for each thread's chunks, concurrently, and re-raises any error.

    kernels: the Warp kernels `work` launches (on `device`, with `block_dim`). Their modules are loaded here, on
    the calling thread, before any worker starts: Warp 1.19's Module.load takes no lock, so workers that all
    launch a not-yet-loaded module at once would each load it (two threads recording a first launch of one
    kernel crashed the process; tests/test_determinism.py)."""
    global _pool
    if len(per_thread) == 1:
        work(0, per_thread[0])
        return
    if kernels:
        import warp as wp  # only here: callers that pass no kernels need no Warp import

        for module in {id(k.module): k.module for k in kernels}.values():
            wp.load_module(module, device=device, block_dim=block_dim)
    if _pool is None or _pool._max_workers < len(per_thread):
        _pool = ThreadPoolExecutor(max_workers=len(per_thread), thread_name_prefix="warpgs-cpu")
    for f in [_pool.submit(work, t, chunks) for t, chunks in enumerate(per_thread)]:
        f.result()
