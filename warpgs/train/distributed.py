"""Data-parallel training over torch.distributed: the process group a Trainer runs in and the collectives it uses.

Every rank holds the whole model and renders its share of each global batch of views. Gradients are summed over
the ranks (each view's loss is already divided by the global batch size, so the sum is the mean over the batch)
and so are the densification statistics (gradient norms and visibility counts; screen radii take the maximum), so
every rank takes the same optimizer step and the same clone/split/prune decisions and no rank holds state of its
own. NCCL on CUDA, gloo on the CPU; launched by torchrun (or `warpgs-train --nproc N`), which sets RANK,
WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT. docs/distributed.md has the whole picture.

A collective that fails (another rank died, or did not arrive within `train.dist_timeout` seconds) raises
`DistributedError` naming this rank, the step's collective and the cause, instead of hanging.
"""
from __future__ import annotations

import datetime
import gc
import hashlib
import os
from typing import Any, Callable, List, Optional, Sequence

import torch
import torch.distributed as dist

from warpgs.render.differentiable_once import differentiable_once

BACKENDS = ("auto", "nccl", "gloo")


class DistributedError(RuntimeError):
    """A collective failed or timed out: another rank stopped, crashed or fell behind."""


def env_world_size() -> int:
    """WORLD_SIZE as torchrun sets it (1 when not launched by it)."""
    try:
        return int(os.environ.get("WORLD_SIZE", "1"))
    except ValueError:
        raise ValueError(f"WORLD_SIZE: expected an integer, got {os.environ['WORLD_SIZE']!r}") from None


class _SumOverRanks(torch.autograd.Function):
    # Our own instead of torch.distributed.nn.functional.all_reduce: that one (deprecated) made about 4 in 10 gloo
    # processes abort at exit ("terminate called without an active exception") after its backward had run.
    @staticmethod
    def forward(ctx, tensor):
        total = tensor.clone()
        dist.all_reduce(total)
        return total

    @staticmethod
    @differentiable_once("the sum over ranks")
    def backward(ctx, grad):
        total = grad.clone()
        dist.all_reduce(total)
        return total


class Ranks:
    """This process's place in the run: `rank`, `world_size`, `local_rank`, the backend, and the collectives the
    Trainer needs. With one process every collective is a no-op returning its input, so single-process training
    runs exactly the code it ran before distributed training existed."""

    def __init__(self, rank: int = 0, world_size: int = 1, local_rank: int = 0, backend: Optional[str] = None,
                 timeout: float = 900.0, owns_group: bool = False, device="cpu"):
        self.rank, self.world_size, self.local_rank = int(rank), int(world_size), int(local_rank)
        self.backend, self.timeout, self.owns_group = backend, float(timeout), owns_group
        # Where tensors that carry no device of their own (scalars, counts) travel: NCCL takes only GPU tensors.
        self.device = torch.device(device)

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """Rank 0: the one that writes checkpoints, the PLY, logs and metrics."""
        return self.rank == 0

    def __repr__(self) -> str:
        return f"Ranks(rank={self.rank}, world_size={self.world_size}, backend={self.backend!r})"

    # ----- sharing work out -------------------------------------------------------------------------------------
    def shard(self, n: int) -> slice:
        """This rank's contiguous part of n items (sizes differ by at most one; the first ranks get the extra)."""
        return self.shard_of(n, self.rank)

    def shard_of(self, n: int, rank: int) -> slice:
        """Rank `rank`'s part of n items, as shard gives it on that rank."""
        base, extra = divmod(int(n), self.world_size)
        start = rank * base + min(rank, extra)
        return slice(start, start + base + (1 if rank < extra else 0))

    def derived_seed(self, seed: int, step: int) -> int:
        """A seed for this rank's own random streams (the global torch/numpy/python generators), from the run's
        seed, the rank and the step the process starts at; the same on a re-run, different between ranks."""
        digest = hashlib.sha256(f"warpgs:{int(seed)}:{self.rank}:{int(step)}".encode()).digest()
        return int.from_bytes(digest[:4], "little")

    # ----- collectives (no-ops on one process) ------------------------------------------------------------------
    def _call(self, what: str, fn: Callable):
        try:
            return fn()
        except RuntimeError as e:  # gloo: "Connection closed by peer", timeouts; NCCL: DistBackendError
            first = next((s.strip() for s in str(e).splitlines() if s.strip()), type(e).__name__)
            raise DistributedError(
                f"rank {self.rank} of {self.world_size}: {what} failed: another rank stopped, crashed or did not "
                f"arrive within train.dist_timeout={self.timeout:g} s ({type(e).__name__}: {first[:300]})") from e

    def all_reduce_(self, tensor: torch.Tensor, op: str = "sum", what: str = "all_reduce") -> torch.Tensor:
        """Sum (or max) `tensor` over the ranks, in place."""
        if self.enabled:
            reduce_op = {"sum": dist.ReduceOp.SUM, "max": dist.ReduceOp.MAX}[op]
            self._call(what, lambda: dist.all_reduce(tensor, op=reduce_op))
        return tensor

    def all_reduce_differentiable(self, tensor: torch.Tensor, what: str = "all_reduce") -> torch.Tensor:
        """The sum of `tensor` over the ranks, as a new tensor whose backward sums the gradients over the ranks too
        (each rank's loss reaches every rank's inputs). Every rank must call it, and run its backward, in step."""
        if not self.enabled:
            return tensor
        return self._call(what, lambda: _SumOverRanks.apply(tensor))

    def broadcast_(self, tensor: torch.Tensor, what: str = "broadcast") -> torch.Tensor:
        """Rank 0's values of `tensor` on every rank, in place."""
        if self.enabled:
            self._call(what, lambda: dist.broadcast(tensor, src=0))
        return tensor

    def broadcast_object(self, obj: Any, what: str = "broadcast") -> Any:
        """Rank 0's `obj` (picklable) on every rank."""
        if not self.enabled:
            return obj
        box = [obj if self.is_main else None]
        self._call(what, lambda: dist.broadcast_object_list(box, src=0))
        return box[0]

    def all_gather_object(self, obj: Any, what: str = "all_gather") -> List[Any]:
        """[every rank's obj], in rank order."""
        if not self.enabled:
            return [obj]
        out: List[Any] = [None] * self.world_size
        self._call(what, lambda: dist.all_gather_object(out, obj))
        return out

    def all_gather_rows(self, tensor: torch.Tensor, what: str = "all_gather") -> torch.Tensor:
        """Every rank's rows of `tensor` ([n_r, ...], same trailing shape and dtype everywhere) concatenated in rank
        order, on every rank. Blocks travel padded to the longest (all_gather takes equal sizes)."""
        if not self.enabled:
            return tensor
        counts = [int(c) for c in self.all_gather_object(int(tensor.shape[0]), what=f"{what}: the sizes")]
        padded = tensor.new_zeros((max(counts),) + tuple(tensor.shape[1:]))
        padded[: tensor.shape[0]] = tensor.detach()
        blocks = [torch.empty_like(padded) for _ in counts]
        self._call(what, lambda: dist.all_gather(blocks, padded))
        return torch.cat([b[:c] for b, c in zip(blocks, counts)])

    def barrier(self, what: str = "barrier") -> None:
        """Wait for every rank. On gloo a monitored barrier, whose error names the ranks that did not arrive."""
        if not self.enabled:
            return
        if self.backend == "gloo":
            timeout = datetime.timedelta(seconds=self.timeout)
            self._call(what, lambda: dist.monitored_barrier(timeout=timeout, wait_all_ranks=True))
        else:
            self._call(what, dist.barrier)

    def check_same(self, value, what: str) -> None:
        """Raise DistributedError unless every rank has the same `value` (cheap: only on refine steps), so ranks
        that drifted apart stop with a message instead of all-reducing tensors of different shapes."""
        if not self.enabled:
            return
        values = self.all_gather_object(value, what=f"checking {what}")
        if any(v != values[0] for v in values):
            raise DistributedError(f"rank {self.rank} of {self.world_size}: ranks disagree on {what}: {values} "
                                   f"(their models drifted apart; see docs/distributed.md)")

    def rank0_first(self, fn: Callable, what: str):
        """fn() on rank 0, then on the others (work that writes caches, e.g. the built-in scene or triangulated
        points, is done once and read by the rest). A failure on rank 0 is reported on every rank."""
        if not self.enabled:
            return fn()
        result, error = None, None
        if self.is_main:
            try:
                result = fn()
            except Exception as e:  # reported to the others, then raised here unchanged
                error = e
        message = self.broadcast_object(None if error is None else f"{type(error).__name__}: {error}",
                                        what=f"waiting for rank 0 ({what})")
        if error is not None:
            raise error
        if message is not None:
            raise DistributedError(f"rank {self.rank} of {self.world_size}: rank 0 failed while {what}: {message}")
        return result if self.is_main else fn()

    # ----- training-specific reductions -------------------------------------------------------------------------
    def all_reduce_gradients(self, params: Sequence[torch.Tensor], scalars: Sequence[float],
                             step: int) -> List[float]:
        """Sum every parameter's .grad over the ranks, in place, and the `scalars` (loss sums, ...); returns the
        summed scalars. Large tensors (the per-primitive parameters) are reduced in place, one collective each,
        so no second copy of the gradients is made; small ones (modules) travel in one flat buffer with the
        scalars. A grad that is None here counts as zeros, and stays None only if it is None on every rank."""
        if not self.enabled:
            return list(scalars)
        present = [p.grad is not None for p in params]
        for p in params:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
        large = [p for p in params if p.numel() >= _SMALL]
        small = [p for p in params if p.numel() < _SMALL]
        for p in large:
            self.all_reduce_(p.grad, what=f"all_reduce of step {step}'s gradients")
        device = params[0].device if params else self.device  # none: a model-parallel run without modules
        head = torch.tensor(list(scalars) + [float(f) for f in present], dtype=torch.float64, device=device)
        flat = torch.cat([head] + [p.grad.reshape(-1).to(torch.float64) for p in small])
        self.all_reduce_(flat, what=f"all_reduce of step {step}'s losses and module gradients")
        offset = len(head)
        for p in small:
            n = p.numel()
            p.grad.copy_(flat[offset:offset + n].view_as(p.grad))
            offset += n
        flags = flat[len(scalars):len(head)]
        for p, anywhere in zip(params, flags.tolist()):
            if anywhere == 0:
                p.grad = None
        return flat[:len(scalars)].tolist()

    def all_reduce_observations(self, obs: dict, step: int) -> dict:
        """Densification statistics of this rank's views -> of the whole batch: gradient norms and counts summed,
        screen radii (pixels and fractions of the image) maxed. The result is the same on every rank."""
        if not self.enabled:
            return obs
        sums = torch.stack([obs["grad"].float(), obs["count"].float()])  # counts stay exact below 2^24
        self.all_reduce_(sums, what=f"all_reduce of step {step}'s densification statistics")
        out = {"grad": sums[0].to(obs["grad"].dtype), "count": sums[1].round().to(obs["count"].dtype),
               "radii": None, "screen": None}
        if obs["radii"] is not None:  # the same config on every rank: all or none computed them
            maxes = torch.stack([obs["radii"], obs["screen"]])
            self.all_reduce_(maxes, op="max", what=f"all_reduce of step {step}'s screen radii")
            out.update(radii=maxes[0], screen=maxes[1])
        return out

    def close(self) -> None:
        """Destroy the process group if this object created it."""
        if self.owns_group:
            shutdown_process_group()
        self.owns_group = False


def shutdown_process_group() -> None:
    """Destroy the default process group, then collect garbage: gloo objects left in reference cycles were otherwise
    freed during interpreter shutdown, which aborted 5-40% of gloo processes at exit ("terminate called without an
    active exception") after a clean run."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()
        gc.collect()


def sync_model(ranks: Ranks, model, device, via=None):
    """Rank 0's model on every rank. Every rank builds the initial model itself (from the same seed, so normally
    identically); its values are then overwritten with rank 0's, in place, so a nondeterministic initialisation
    (threaded SfM, a user's model) cannot start the ranks apart. Where the shapes differ, rank 0's whole model
    replaces this one. Returns the model to use, on `device`. via: the device the collectives run on when it is not
    the model's (NCCL needs the GPU; a model-parallel run keeps the whole model in CPU memory), one parameter at a
    time."""
    if not ranks.enabled:
        return model
    via = torch.device(device if via is None else via)
    shapes = {name: tuple(p.shape) for name, p in model.params.items()}
    if all(s == shapes for s in ranks.all_gather_object(shapes, what="comparing the initial models")):
        with torch.no_grad():
            for name, p in model.params.items():
                values = p.data if p.device == via else p.data.to(via)
                ranks.broadcast_(values, what=f"broadcasting the initial {name}")
                if values is not p.data:
                    p.data.copy_(values)
        return model
    from warpgs.model.gaussians import GaussianModel

    state = ranks.broadcast_object(model.to_dict() if ranks.is_main else None, what="broadcasting the initial model")
    return model if ranks.is_main else GaussianModel.from_dict(state, device=device)


# Tensors with fewer elements than this are reduced together in one flat float64 buffer.
_SMALL = 1 << 16


def setup_ranks(device, *, backend: str = "auto", timeout: float = 900.0) -> tuple:
    """(Ranks, device) for this process. Launched by torchrun (WORLD_SIZE > 1) or inside a process group that is
    already initialised: join it, with NCCL on CUDA and gloo on the CPU (`backend` forces one); a CUDA device
    becomes cuda:LOCAL_RANK unless the config names an index. Otherwise one process: Ranks() and `device`."""
    if backend not in BACKENDS:
        raise ValueError(f"train.dist_backend: expected one of {list(BACKENDS)}, got {backend!r}")
    if not timeout > 0:
        raise ValueError(f"train.dist_timeout: expected a positive number of seconds, got {timeout!r}")
    device = torch.device(device)
    initialised = dist.is_available() and dist.is_initialized()
    if not initialised and env_world_size() <= 1:
        return Ranks(timeout=timeout), device
    if not dist.is_available():
        raise ValueError("WORLD_SIZE > 1 but this torch build has no torch.distributed")
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", local_rank)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    owns = False
    if not initialised:
        chosen = backend if backend != "auto" else ("nccl" if device.type == "cuda" else "gloo")
        if chosen == "nccl" and device.type != "cuda":
            raise ValueError("train.dist_backend: 'nccl' needs CUDA devices (use gloo on the CPU)")
        dist.init_process_group(chosen, timeout=datetime.timedelta(seconds=timeout))
        owns = True
    chosen = dist.get_backend()
    ranks = Ranks(dist.get_rank(), dist.get_world_size(), local_rank, chosen, timeout, owns,
                  device=device if chosen == "nccl" else "cpu")
    return ranks, device


__all__ = ["Ranks", "DistributedError", "setup_ranks", "sync_model", "env_world_size", "BACKENDS"]
