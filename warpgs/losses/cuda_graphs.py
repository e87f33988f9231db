"""A loss's torch ops replayed from CUDA graphs, one per input shape.

On a GPU a training step's D-SSIM is a dozen small kernels forward and more backward, each launched from
Python: the GPU finishes them faster than the host issues them and waits (benchmarks/step_trace.py put 1.4 ms
of a 1M-primitive step's idle GPU time on the SSIM's launches). Replaying them from a graph
(torch.cuda.make_graphed_callables, forward and backward) issues each direction with one launch.

Only where it is safe: CUDA tensors, grad enabled and the first argument requiring grad (a training step);
anything else — CPU, evaluation, more distinct shapes than `max_graphs` — calls the function as written.
The function must be graph-safe: no host reads, no shapes that depend on values. WARPGS_LOSS_GRAPHS=0 turns
the graphs off (for A/B runs and debugging).

The output of a replay is the graph's own buffer, overwritten by the next replay: callers use it at once
(`1 - ssim(...)`), or return a copy (a loss term's value is kept by compute_losses), they do not keep it.
A graph's backward differentiates its last replay, so each replay's backward must run before the same graph
replays again (the trainer's steps do: render, loss and backward per view); two forward calls of one signature
before one backward would give the first call wrong gradients, silently. A capture that fails (an op a graph
cannot hold) warns and leaves those inputs' calls to the function as written.

KeyedGraphs: ShapeGraphs per Python-level key, for a function whose settings or optional arguments are fixed
when its graph is captured (the Marr depth terms': their settings, whether a confidence map comes).
"""
from __future__ import annotations

import os
import warnings
from typing import Callable, Optional

import torch


def loss_graphs_enabled() -> bool:
    return os.environ.get("WARPGS_LOSS_GRAPHS", "1").strip().lower() not in ("0", "false", "off", "no")


class ShapeGraphs:
    """fn(*tensors) -> tensor, replayed from a graph per (shape, dtype, device, requires_grad) of its arguments."""

    def __init__(self, fn: Callable, max_graphs: int = 4, capture: Optional[Callable] = None):
        self.fn = fn
        self.max_graphs = int(max_graphs)
        self.capture = capture or _capture
        self.graphs = {}

    def __call__(self, *args):
        if not (loss_graphs_enabled() and _is_training_call(args)):
            return self.fn(*args)
        return self.lookup(args)(*args)

    def lookup(self, args) -> Callable:
        """The graphed callable for these arguments' signature (captured on first use), or fn itself once
        max_graphs signatures hold graphs: each graph keeps its own buffers, so a capture of many image sizes
        does not fill the GPU with them."""
        key = tuple((tuple(a.shape), a.dtype, a.device, a.requires_grad) for a in args)
        graphed = self.graphs.get(key)
        if graphed is None:
            if len(self.graphs) >= self.max_graphs:
                return self.fn
            sample = tuple(a.detach().clone().requires_grad_(a.requires_grad) for a in args)
            try:
                graphed = self.capture(self.fn, sample)
            except Exception as e:  # an op a graph cannot hold must cost speed, not the training run
                name = getattr(self.fn, "__name__", "a loss")
                warnings.warn(f"{name}: CUDA graph capture failed ({type(e).__name__}: {e}); it runs as written "
                              "for these inputs", RuntimeWarning)
                graphed = self.fn
            self.graphs[key] = graphed
        return graphed


class KeyedGraphs:
    """fn(key, *tensors): ShapeGraphs of make(key), a function of the tensors with whatever the key stands for
    (settings, which optional maps are given) fixed in it, so a capture never replays a stale setting. The
    `max_keys` keys used last keep their graphs; an older key's are dropped (settings changed between benchmark
    runs), which frees their buffers."""

    def __init__(self, make: Callable, max_keys: int = 2, max_graphs: int = 4, capture: Optional[Callable] = None):
        self.make = make
        self.max_keys = int(max_keys)
        self.max_graphs = int(max_graphs)
        self.capture = capture
        self.keys = {}  # key -> ShapeGraphs, least recently used first

    def __call__(self, key, *args):
        return self.graphs_for(key)(*args)

    def graphs_for(self, key) -> ShapeGraphs:
        graphs = self.keys.pop(key, None)
        if graphs is None:
            while len(self.keys) >= self.max_keys:
                self.keys.pop(next(iter(self.keys)))
            graphs = ShapeGraphs(self.make(key), self.max_graphs, self.capture)
        self.keys[key] = graphs  # the most recently used last
        return graphs


def _is_training_call(args) -> bool:
    return (torch.is_grad_enabled() and all(torch.is_tensor(a) and a.is_cuda for a in args)
            and args[0].requires_grad)


def _capture(fn: Callable, sample: tuple) -> Callable:
    with warnings.catch_warnings():
        # the capture's warm-up runs on a side stream; torch warns that its gradient accumulation crosses streams
        warnings.filterwarnings("ignore", message=".*AccumulateGrad node's stream.*")
        return torch.cuda.make_graphed_callables(fn, sample)
