"""Sharded checkpoints of train.parallel=model: every rank writes the checkpoint of its own share (its rows of the
model, of Adam's moments and of the densification statistics, plus the replicated rest) and rank 0 then writes a
small index in place of checkpoint.pt. No rank ever holds the whole model to save it.

    checkpoint.pt                                  the index: step, the shard files, their row counts
    checkpoint-shards/step-00000500/rank-0-of-2.pt the share of rank 0 of 2 at step 500 (a checkpoint of its own)

The index is written last, atomically, after every shard is on disk: until then checkpoint.pt is the previous
checkpoint (single file or index, whose shard folder is removed only after the new index is in place), so a crash
while saving leaves the previous checkpoint whole. Reading one (load_checkpoint) puts the shards together into the
dict a single-file checkpoint holds, so it resumes on any number of processes, in either parallel mode."""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import List

import torch

from warpgs.train.optim import MOMENTS
from warpgs.train.densify_stats import STATISTICS

INDEX_VERSION = 3  # checkpoint.VERSION: readers older than the sharded format refuse the index by its version


def shard_folder(index_path) -> Path:
    """The folder of an index's shards: checkpoint.pt -> checkpoint-shards."""
    index_path = Path(index_path)
    return index_path.with_name(f"{index_path.stem}-shards")


def shard_file(index_path, step: int, rank: int, world_size: int) -> Path:
    return shard_folder(index_path) / f"step-{int(step):08d}" / f"rank-{rank}-of-{world_size}.pt"


def index_state(index_path, step: int, rows: List[int]) -> dict:
    """What checkpoint.pt holds for the shards of `step`, written by each rank with `rows` primitives."""
    world = len(rows)
    files = [shard_file(index_path, step, r, world).relative_to(Path(index_path).parent).as_posix()
             for r in range(world)]
    return {"version": INDEX_VERSION, "step": int(step), "shards": {"files": files, "rows": [int(n) for n in rows]}}


def remove_other_steps(index_path, keep_step) -> None:
    """Shard folders of steps other than `keep_step` (None: all), once the index no longer names them."""
    folder = shard_folder(index_path)
    if not folder.is_dir():
        return
    keep = None if keep_step is None else f"step-{int(keep_step):08d}"
    for step_dir in folder.iterdir():
        if step_dir.name != keep:
            shutil.rmtree(step_dir, ignore_errors=True)
    if keep is None:
        shutil.rmtree(folder, ignore_errors=True)


def assemble(index_path, index: dict, load) -> dict:
    """The single-file checkpoint dict from an index and its shard files (read with `load(path)`): rank 0's
    replicated state (modules, counters, RNG states, config, ...) with every per-primitive tensor concatenated
    over the shards in rank order."""
    index_path = Path(index_path)
    info = index["shards"]
    files, rows = list(info["files"]), [int(n) for n in info["rows"]]
    if not files or len(files) != len(rows):
        raise ValueError(f"{index_path}: a sharded checkpoint index with {len(files)} files and {len(rows)} row counts")
    shards = []
    for rank, (name, n) in enumerate(zip(files, rows)):
        path = index_path.parent / name
        if not path.is_file():
            raise FileNotFoundError(f"{index_path}: shard {path} of rank {rank} is missing (every rank writes its "
                                    f"own shard into the output folder: across machines it must be shared storage, "
                                    f"see docs/distributed.md)")
        shard = load(path)
        got = _rows(shard)
        if got != n or shard.get("step") != index["step"]:
            raise ValueError(f"{path}: shard of step {shard.get('step')} with {got} rows; the index {index_path} "
                             f"says step {index['step']} with {n}")
        shards.append(shard)
    whole = dict(shards[0])
    whole["model"] = {**shards[0]["model"],
                      "params": {name: torch.cat([s["model"]["params"][name] for s in shards])
                                 for name in shards[0]["model"]["params"]}}
    whole["optimizer"] = _optimizer(shards)
    whole["strategy"] = {**shards[0]["strategy"],
                         **{k: torch.cat([s["strategy"][k] for s in shards])
                            for k in STATISTICS if k in shards[0]["strategy"]}}
    return whole


def _rows(shard: dict) -> int:
    return int(shard["model"]["params"]["means"].shape[0])


def _optimizer(shards: list) -> dict:
    """Adam's state_dict over the whole model: each group's per-row moments concatenated (zeros for a shard that
    has none yet), its scalars (`step`) from the first shard that has them."""
    first = shards[0]["optimizer"]
    state = {}
    for group in first["param_groups"]:
        (idx,) = group["params"]
        present = [s["optimizer"]["state"].get(idx, {}) for s in shards]
        if not any(present):
            continue
        merged = dict(next(p for p in present if p))
        for key in MOMENTS:
            if key in merged:
                merged[key] = torch.cat([
                    p[key] if key in p else torch.zeros_like(s["model"]["params"][group["name"]])
                    for p, s in zip(present, shards)])
        state[idx] = merged
    return {"state": state, "param_groups": first["param_groups"]}
