"""`warpgs-train --nproc N ...`: the same run as `torchrun --standalone --nproc_per_node=N -m warpgs.cli train ...`,
started through torch.distributed.run itself (no launcher of our own): N worker processes on this machine, one
per GPU with NCCL, or gloo on the CPU. torchrun watches the workers; when one fails it stops the others and
prints which rank failed and how, and this returns that rank's exit code."""
from __future__ import annotations

import sys
from typing import List, Sequence

from warpgs.train.distributed import env_world_size

# Exit codes warpgs-train gives a worker's failure (config, non-finite, distributed, Ctrl-C); others become 1.
_KNOWN_EXITS = (2, 3, 4, 130)


def strip_nproc(argv: Sequence[str]) -> List[str]:
    """argv without `--nproc N` / `--nproc=N` (the workers are the N processes)."""
    out, skip = [], False
    for item in argv:
        if skip:
            skip = False
        elif item == "--nproc":
            skip = True
        elif not item.startswith("--nproc="):
            out.append(item)
    return out


def torchrun_args(nproc: int, argv: Sequence[str]) -> List[str]:
    """torch.distributed.run's command line for N workers of `python -m warpgs.cli train <argv>`."""
    return ["--standalone", f"--nproc_per_node={int(nproc)}", "-m", "warpgs.cli", "train", *strip_nproc(argv)]


def check_nproc(nproc: int) -> None:
    """ValueError unless `--nproc N` can be honoured here. N = 1 is the plain single-process run, which the caller
    goes on with itself (nothing to launch)."""
    if nproc < 1:
        raise ValueError(f"--nproc: expected a positive number of processes, got {nproc}")
    if env_world_size() > 1:
        raise ValueError("--nproc: this process is already one of a distributed run (WORLD_SIZE is set, e.g. by "
                         "torchrun); drop --nproc")


def launch_train(nproc: int, argv: Sequence[str]) -> int:
    """Run warpgs-train with `argv` on `nproc` (at least 2) local processes; returns an exit code (0: every rank
    finished)."""
    check_nproc(nproc)
    if nproc == 1:
        raise ValueError("--nproc 1 runs in this process: the caller trains without launching workers")
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.run import main as torchrun_main

    try:
        torchrun_main(torchrun_args(nproc, argv))
    except ChildFailedError as e:  # torchrun has printed the failing rank, its exit code and the traceback
        rank, failure = e.get_first_failure()
        code = failure.exitcode
        print(f"warpgs-train: error: a worker failed (rank {rank}, exit code {code}); the other ranks "
              f"were stopped", file=sys.stderr)
        return code if code in _KNOWN_EXITS else 1
    return 0
