"""Depth and inverse-depth maps on disk: OpenEXR, .npy and 16-bit PNG in; OpenEXR and 16-bit PNG out.

Value conventions when reading (whatever the format):
- NaN or a negative value is an error (naming the file): it means a broken export, not "no data".
- 0 means "no measurement" and is marked invalid.
- +inf depth means "infinitely far" (sky); it becomes inverse depth 0 and stays valid.
Our own EXRs carry an explicit validity channel, so they can also store valid zeros.
"""
from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Optional

import numpy as np
from PIL import Image, UnidentifiedImageError

from warpgs.data.errors import PathLike, SceneError, require_file

DEPTH_EXTENSIONS = (".exr", ".npy", ".png")
KINDS = ("depth", "inverse_depth")
# Channel names looked for, in order, in a single-map EXR.
_VALUE_CHANNELS = ("Z", "inv_depth", "depth", "Y", "R", "V")
_VALID_CHANNEL = "valid"
_KIND_ATTRIBUTE = "warpgs_kind"
# A corrupted EXR header can declare any data window, and the reader allocates it before decoding a pixel;
# no depth map is anywhere near 2^28 pixels (16384 x 16384), so larger windows are refused up front.
MAX_EXR_PIXELS = 1 << 28


def _open_exr(path: Path, **kwargs):
    """OpenEXR.File of `path` once its header's data window has been checked (SceneError naming the file)."""
    import OpenEXR  # lazily: only depth files need it

    try:
        with OpenEXR.File(str(path), header_only=True) as exr:
            (x0, y0), (x1, y1) = exr.header()["dataWindow"]
    except Exception as exc:  # OpenEXR raises RuntimeError for truncated/corrupt files
        raise SceneError(path, f"unreadable or truncated EXR ({exc})") from exc
    width, height = int(x1) - int(x0) + 1, int(y1) - int(y0) + 1
    if width < 1 or height < 1 or width * height > MAX_EXR_PIXELS:
        raise SceneError(path, f"EXR data window {width}x{height} is empty or implausibly large (corrupt header?)")
    try:
        return OpenEXR.File(str(path), **kwargs)
    except Exception as exc:
        raise SceneError(path, f"unreadable or truncated EXR ({exc})") from exc


def _read_exr(path: Path) -> tuple[np.ndarray, Optional[np.ndarray], Optional[str]]:
    try:
        with _open_exr(path, separate_channels=True) as exr:
            header = dict(exr.header())  # the File clears its header dict on close
            channels = {name: np.array(ch.pixels) for name, ch in exr.channels().items()}
    except SceneError:
        raise
    except Exception as exc:  # OpenEXR raises RuntimeError for truncated/corrupt files
        raise SceneError(path, f"unreadable or truncated EXR ({exc})") from exc
    value_name = next((c for c in _VALUE_CHANNELS if c in channels), None)
    if value_name is None:
        if len(channels) != 1:
            raise SceneError(path, f"cannot tell which EXR channel holds depth among {sorted(channels)}")
        value_name = next(iter(channels))
    valid = channels.get(_VALID_CHANNEL)
    values = channels[value_name]
    if not np.issubdtype(values.dtype, np.number):
        raise SceneError(path, f"EXR channel {value_name!r} is not numeric ({values.dtype})")
    if valid is not None and valid.shape != values.shape:  # subsampled channels differ in size
        raise SceneError(path, f"EXR channels {value_name!r} {values.shape} and {_VALID_CHANNEL!r} {valid.shape} differ")
    kind = header.get(_KIND_ATTRIBUTE)
    kind = kind.decode("utf-8", "replace") if isinstance(kind, bytes) else kind
    return values.astype(np.float32), None if valid is None else valid > 0.5, kind


def _read_png16(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as img:
            img.load()
            if img.mode not in ("I;16", "I;16B", "I;16L", "I"):
                raise SceneError(path, f"depth PNG must be 16-bit single channel, got mode {img.mode}")
            return np.array(img).astype(np.float32)
    except UnidentifiedImageError as exc:
        raise SceneError(path, f"not a readable PNG ({exc})") from exc
    except OSError as exc:
        raise SceneError(path, f"truncated or corrupt depth PNG ({exc})") from exc


def _read_npy(path: Path) -> np.ndarray:
    # Memory-mapped first: a corrupted shape then fails against the file size instead of allocating what the
    # header claims (np.load reads into an array of the declared size).
    try:
        arr = np.load(path, allow_pickle=False, mmap_mode="r")
        if not isinstance(arr, np.ndarray):  # an .npz archive
            raise SceneError(path, "expected a single .npy array, not an .npz archive")
        arr = np.array(arr)
    except SceneError:
        raise
    except Exception as exc:  # numpy's header parser raises ValueError, SyntaxError, tokenize.TokenError, ...
        raise SceneError(path, f"unreadable or truncated .npy ({type(exc).__name__}: {exc})") from exc
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise SceneError(path, f"depth array has non-numeric (or complex) dtype {arr.dtype}")
    return arr.astype(np.float32)


def read_depth_file(path: PathLike, scale: float = 1.0) -> tuple[np.ndarray, Optional[np.ndarray], Optional[str]]:
    """Raw map [H, W] float32 times `scale`, its validity channel if the file has one, and the kind it declares."""
    path = require_file(path, "depth map")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        values, valid, kind = _read_exr(path)
    elif suffix == ".npy":
        values, valid, kind = _read_npy(path), None, None
    elif suffix == ".png":
        values, valid, kind = _read_png16(path), None, None
    else:
        raise SceneError(path, f"unsupported depth format {suffix!r}; use one of {DEPTH_EXTENSIONS}")
    if values.ndim != 2:
        raise SceneError(path, f"depth map must be 2-D (H, W), got shape {values.shape}")
    n_nan = int(np.isnan(values).sum())
    if n_nan:
        raise SceneError(path, f"depth map contains {n_nan} NaN value(s); mark missing pixels with 0 instead")
    if (values < 0).any():
        raise SceneError(path, f"depth map contains negative values (min {values.min():g})")
    return values * np.float32(scale), valid, kind


def read_inverse_depth(path: PathLike, kind: Optional[str] = None, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Any supported depth file -> (inverse depth [H, W] float32, valid [H, W] bool).

    `kind` says whether the file stores "depth" or "inverse_depth"; EXRs we wrote declare it themselves.
    """
    values, valid, declared = read_depth_file(path, scale)
    kind = kind or declared
    if kind not in KINDS:
        raise SceneError(path, f"say whether this file holds 'depth' or 'inverse_depth' (kind={kind!r})")
    if valid is None:
        valid = values > 0
    if kind == "depth":
        with np.errstate(divide="ignore"):
            inv = np.where(valid, 1.0 / np.maximum(values, 1e-30), 0.0).astype(np.float32)  # inf depth -> 0
    else:
        if np.isinf(values).any():
            raise SceneError(path, "inverse depth map contains infinite values")
        inv = np.where(valid, values, 0.0).astype(np.float32)
    return inv, valid


def read_depth(path: PathLike, kind: Optional[str] = None, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Any supported depth file -> (depth [H, W] float32, valid [H, W] bool); sky/infinitely far is +inf."""
    inv, valid = read_inverse_depth(path, kind, scale)
    with np.errstate(divide="ignore"):
        depth = np.where(valid, 1.0 / inv, 0.0).astype(np.float32)
    return depth, valid


def write_exr(path: PathLike, values: np.ndarray, kind: str, valid: Optional[np.ndarray] = None) -> Path:
    """Write a depth ("depth") or inverse-depth ("inverse_depth") map [H, W] as float32 EXR, atomically.

    The kind is stored in the header so readers need not be told; `valid` (bool [H, W]) adds a validity channel.
    Extra channels (e.g. normals [H, W, 3]) can be written with `write_exr_channels`.
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    values = np.asarray(values, dtype=np.float32)
    if values.ndim != 2:
        raise ValueError(f"{path}: depth map must be 2-D, got shape {values.shape}")
    if np.isnan(values).any():
        raise ValueError(f"{path}: refusing to write NaN into a depth map")
    channels = {"Z": values}
    if valid is not None:
        channels[_VALID_CHANNEL] = np.asarray(valid, dtype=np.float32)
    return write_exr_channels(path, channels, {_KIND_ATTRIBUTE: kind})


def write_depth_png16(path: PathLike, depth: np.ndarray, scale: float, valid: Optional[np.ndarray] = None) -> int:
    """Write depth [H, W] as a 16-bit PNG of round(depth * scale), atomically; 0 marks pixels without depth (not
    `valid`, not finite, or beyond 65535 / scale). A valid depth under half a level is written as level 1, the
    nearest depth the format holds, not as 0 (which would read as "no depth"). Read back with read_depth(path,
    "depth", scale=1 / scale). Returns how many valid pixels were beyond the range (and written as 0)."""
    from warpgs.utils.atomic_file import atomic_write_bytes

    if not 0 < scale < float("inf"):  # inf would write every pixel as "no depth"
        raise ValueError(f"{path}: depth scale must be positive and finite, got {scale}")
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"{path}: depth map must be 2-D, got shape {depth.shape}")
    ok = np.isfinite(depth) & (depth > 0) if valid is None else np.asarray(valid, bool) & np.isfinite(depth)
    levels = np.round(np.where(ok, depth, 0.0) * scale)
    beyond = ok & (levels > 65535)
    levels = np.where(ok & ~beyond & (levels >= 0), np.maximum(levels, 1), 0).astype(np.uint16)
    buf = io.BytesIO()
    Image.fromarray(levels).save(buf, format="PNG")  # uint16 arrays become mode I;16
    atomic_write_bytes(path, buf.getvalue())
    return int(beyond.sum())


def write_exr_channels(path: PathLike, channels: dict, attributes: Optional[dict] = None) -> Path:
    import OpenEXR

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(attributes or {})
    pixels = {name: np.ascontiguousarray(arr, dtype=np.float32) for name, arr in channels.items()}
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.exr")
    with OpenEXR.File(header, pixels) as exr:
        exr.write(str(tmp))
    os.replace(tmp, path)
    return path


def read_exr_channels(path: PathLike) -> dict:
    """All channels of an EXR as float32 arrays (an [H, W, 3] array for an RGB group such as normals)."""
    path = require_file(path, "EXR file")
    try:
        with _open_exr(path) as exr:
            return {name: np.array(ch.pixels, dtype=np.float32) for name, ch in exr.channels().items()}
    except SceneError:
        raise
    except Exception as exc:
        raise SceneError(path, f"unreadable or truncated EXR ({exc})") from exc
