"""Training checkpoints: written atomically (temp file in the same folder, fsync, os.replace), so a reader —
or a resumed run after Ctrl-C or a crash — sees the previous checkpoint or the new one, never half of one.
Also the RNG states a bit-exact resume needs."""
from __future__ import annotations

import io
import random
from pathlib import Path

import numpy as np
import torch

from warpgs.utils.atomic_file import atomic_write_bytes

FORMAT = "warpgs-checkpoint"
VERSION = 1


def save_checkpoint(path, state: dict) -> Path:
    buf = io.BytesIO()
    torch.save({"format": FORMAT, "version": VERSION, **state}, buf)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


def load_checkpoint(path, map_location="cpu") -> dict:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    try:
        state = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as e:  # truncated or foreign file
        raise ValueError(f"{path}: not a readable checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise ValueError(f"{path}: not a warpgs checkpoint")
    if state.get("version", 0) > VERSION:
        raise ValueError(f"{path}: checkpoint version {state['version']} is newer than this warpgs ({VERSION})")
    return state


def rng_state() -> dict:
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)


def leftover_temp_files(folder) -> list:
    """Temp files an interrupted atomic write may leave (the writer removes them; a hard kill may not)."""
    folder = Path(folder)
    return sorted(p for p in folder.glob(".*.tmp")) if folder.is_dir() else []


__all__ = ["save_checkpoint", "load_checkpoint", "rng_state", "set_rng_state", "seed_everything",
           "leftover_temp_files"]
