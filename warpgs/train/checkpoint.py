"""Training checkpoints: written atomically (temp file in the same folder, fsync, os.replace), so a reader —
or a resumed run after Ctrl-C or a crash — sees the previous checkpoint or the new one, never half of one.
Also the RNG states a bit-exact resume needs.

Loading never runs code from the file: checkpoints are read with ``torch.load(weights_only=True)``, which
unpickles tensors and plain data (dicts, lists, tuples, str, numbers, None) and nothing else. What `save_checkpoint`
writes is exactly that: numpy values are turned into tensors or Python numbers first (the numpy RNG state
included), and anything else is refused at save time, naming its key, rather than written into a file that
could not be loaded back. Version-1 checkpoints (numpy's uint32 RNG key array in them) still load: for those,
and only while loading, the numpy array reconstructor and the uint32 dtype are allowed too."""
from __future__ import annotations

import collections
import io
import pickle
import random
import re
from pathlib import Path, PurePath

import numpy as np
import torch

from warpgs.utils.atomic_file import atomic_write_bytes

FORMAT = "warpgs-checkpoint"
VERSION = 3  # the newest this reads. 3: an index of per-rank shards (train/sharded_checkpoint.py); 2: plain data
SINGLE_FILE_VERSION = 2  # only (the numpy RNG key as a tensor); 1: the key as a numpy array

# What version-1 files hold beyond tensors and plain data: numpy's MT19937 key, a uint32 array.
_V1_NUMPY_GLOBALS = [np.ndarray, np.dtype, type(np.dtype(np.uint32))]
try:  # numpy >= 2
    from numpy._core.multiarray import _reconstruct as _np_reconstruct
except ImportError:  # numpy 1.x
    from numpy.core.multiarray import _reconstruct as _np_reconstruct
_V1_NUMPY_GLOBALS.insert(0, _np_reconstruct)


class UnsafeCheckpointError(ValueError):
    """A checkpoint whose unpickling would construct or call something other than tensors and plain data."""


def save_checkpoint(path, state: dict) -> Path:
    payload = _plain({"format": FORMAT, "version": SINGLE_FILE_VERSION, **state}, "checkpoint")
    buf = io.BytesIO()
    torch.save(payload, buf)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


def load_checkpoint(path, map_location="cpu") -> dict:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    try:
        with torch.serialization.safe_globals(_V1_NUMPY_GLOBALS):
            state = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        refused = _refused_global(str(e))
        if refused is not None:
            raise UnsafeCheckpointError(
                f"{path}: refused to load: {refused}. No warpgs checkpoint holds that, and unpickling anything "
                f"beyond tensors and plain data can execute arbitrary code, so warpgs reads checkpoints with "
                f"torch.load(weights_only=True)") from None
        raise ValueError(f"{path}: not a readable checkpoint ({_first_line(e)})") from None
    except Exception as e:  # truncated or foreign file
        raise ValueError(f"{path}: not a readable checkpoint ({type(e).__name__}: {_first_line(e)})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise ValueError(f"{path}: not a warpgs checkpoint")
    if state.get("version", 0) > VERSION:
        raise ValueError(f"{path}: checkpoint version {state['version']} is newer than this warpgs ({VERSION})")
    if "shards" in state:  # the index of a model-parallel run's shards: put together as one file would hold it
        from warpgs.train.sharded_checkpoint import assemble

        return assemble(path, state, lambda shard: load_checkpoint(shard, map_location))
    return state


def _refused_global(message: str):
    """What torch's weights-only unpickler refused, as 'it would ...' (None for other errors)."""
    m = re.search(r"GLOBAL ([\w.]+)", message)  # 'Unsupported global: GLOBAL x' / 'unsupported GLOBAL x whose ...'
    if m:
        return f"it would call or build {m.group(1)}"
    m = re.search(r"but got (<class '[\w.]+'>|[\w.]+)", message)  # 'Can only build Tensor, ... but got <class>'
    if m:
        return f"it would build a {m.group(1).strip('<>').replace('class ', '')}"
    m = re.search(r"(Unsupported operand \S+|Trying to call reduce for unrecognized function \S+)", message)
    return f"it uses a pickle feature outside tensors and plain data ({m.group(1)})" if m else None


def _first_line(e: BaseException) -> str:
    lines = [s.strip() for s in str(e).splitlines() if s.strip()]
    for line in lines:  # torch's weights-only messages put the cause on a 'WeightsUnpickler error:' line
        if line.startswith("WeightsUnpickler error:"):
            return line
    return re.split(r"(?<=\.)\s", lines[0])[0] if lines else type(e).__name__  # its first sentence


def _plain(obj, where: str):
    """obj with numpy values as tensors / Python numbers, paths as str and tensors in CPU memory; a TypeError
    naming the key for anything torch.load(weights_only=True) would refuse."""
    if isinstance(obj, np.generic) and obj.dtype.kind in "biufUS":  # before float: np.float64 is one
        return obj.item()
    if isinstance(obj, torch.Tensor):  # in CPU memory, so the file loads anywhere (no-op for CPU tensors)
        return obj.detach().cpu()
    if obj is None or type(obj) in (bool, int, float, str, bytes) or isinstance(
            obj, (torch.dtype, torch.device, torch.Size)):
        return obj
    if isinstance(obj, dict):  # OrderedDict (state_dicts) stays one: the weights-only loader knows it
        out = {k: _plain(v, f"{where}[{k!r}]") for k, v in obj.items()}
        return collections.OrderedDict(out) if isinstance(obj, collections.OrderedDict) else out
    if isinstance(obj, (list, tuple)) and type(obj) in (list, tuple):
        items = [_plain(v, f"{where}[{i}]") for i, v in enumerate(obj)]
        return items if isinstance(obj, list) else tuple(items)
    if isinstance(obj, np.ndarray) and obj.dtype.kind in "biuf":
        dtype = _TORCHABLE.get(obj.dtype.str[1:], obj.dtype.newbyteorder("="))
        return torch.from_numpy(np.ascontiguousarray(obj).astype(dtype))
    if isinstance(obj, PurePath):
        return str(obj)
    raise TypeError(f"{where}: a {type(obj).__module__}.{type(obj).__qualname__} cannot go into a checkpoint "
                    f"(checkpoints hold tensors and plain data only, so that loading one cannot run code)")


# numpy dtypes torch has no tensor type for, widened losslessly.
_TORCHABLE = {"u2": np.int32, "u4": np.int64}


def rng_state() -> dict:
    """The global RNG states, as tensors and plain data (numpy's MT19937 key as an int64 tensor)."""
    kind, key, pos, has_gauss, gauss = np.random.get_state()
    state = {"torch": torch.get_rng_state(),
             "numpy": (str(kind), torch.from_numpy(key.astype(np.int64)), int(pos), int(has_gauss), float(gauss)),
             "python": random.getstate()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    kind, key, pos, has_gauss, gauss = state["numpy"]
    key = key.numpy() if torch.is_tensor(key) else np.asarray(key)  # version 1: the numpy array itself
    np.random.set_state((kind, key.astype(np.uint32), int(pos), int(has_gauss), float(gauss)))
    random.setstate(_as_tuples(state["python"]))
    if "cuda" in state and torch.cuda.is_available():
        # One state per GPU the writer saw; a process that sees fewer (another machine, CUDA_VISIBLE_DEVICES)
        # takes those it has.
        for index, cuda_state in enumerate(state["cuda"][:torch.cuda.device_count()]):
            torch.cuda.set_rng_state(cuda_state, index)


def _as_tuples(v):
    """random.setstate wants (version, tuple of ints, gauss): tuples all the way down."""
    return tuple(_as_tuples(x) for x in v) if isinstance(v, (list, tuple)) else v


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)


def leftover_temp_files(folder) -> list:
    """Temp files an interrupted atomic write may leave (the writer removes them; a hard kill may not)."""
    folder = Path(folder)
    return sorted(p for p in folder.glob(".*.tmp")) if folder.is_dir() else []


__all__ = ["save_checkpoint", "load_checkpoint", "rng_state", "set_rng_state", "seed_everything",
           "leftover_temp_files", "UnsafeCheckpointError"]
