"""Reading and writing images, label maps and masks, with errors that name the file."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import numpy as np
from PIL import Image, UnidentifiedImageError

from warpgs.data.errors import PathLike, SceneError, require_file

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG", ".tif", ".tiff", ".bmp", ".webp")


def _open(path: Path, what: str) -> Image.Image:
    require_file(path, what)
    try:
        img = Image.open(path)
        img.load()  # decode now so truncation surfaces here, not later
    except UnidentifiedImageError as exc:
        raise SceneError(path, f"not a readable {what} ({exc})") from exc
    except (OSError, SyntaxError, ValueError) as exc:
        raise SceneError(path, f"truncated or corrupt {what} ({exc})") from exc
    return img


def image_size(path: PathLike, what: str = "image") -> tuple[int, int]:
    """(width, height) from the file header only."""
    path = require_file(path, what)
    try:
        with Image.open(path) as img:
            return img.size
    except UnidentifiedImageError as exc:
        raise SceneError(path, f"not a readable {what} ({exc})") from exc
    except OSError as exc:
        raise SceneError(path, f"corrupt {what} header ({exc})") from exc


def to_float(arr: np.ndarray) -> np.ndarray:
    """8/16-bit codes -> float32 in [0, 1], as images are decoded (float arrays as float32)."""
    if arr.dtype == np.uint8:
        return arr.astype(np.float32) / 255.0
    if arr.dtype == np.uint16:
        return arr.astype(np.float32) / 65535.0
    if np.issubdtype(arr.dtype, np.integer):  # PIL's 32-bit "I" mode holds 16-bit PNGs
        return np.clip(arr.astype(np.float32) / 65535.0, 0.0, 1.0)
    return arr.astype(np.float32)


def read_image(path: PathLike, background: Optional[np.ndarray] = None) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Image -> (rgb [H, W, 3] float32 in [0, 1], alpha [H, W] float32 or None).

    RGBA images are composited over `background` (RGB in [0, 1]; default black) and their alpha returned,
    so transparent-background datasets (NeRF synthetic) get a mask for free.
    """
    path = Path(path)
    img = _open(path, "image")
    mode = img.mode
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        grey = to_float(np.array(img))
        return np.repeat(grey[..., None], 3, axis=2), None
    has_alpha = mode in ("RGBA", "LA", "PA") or (mode == "P" and "transparency" in img.info)
    arr = to_float(np.array(img.convert("RGBA" if has_alpha else "RGB")))
    if not has_alpha:
        return np.ascontiguousarray(arr), None
    rgb, alpha = arr[..., :3], arr[..., 3]
    bg = np.zeros(3, np.float32) if background is None else np.asarray(background, np.float32).reshape(3)
    return rgb * alpha[..., None] + bg * (1.0 - alpha[..., None]), alpha


def read_label_map(path: PathLike) -> np.ndarray:
    """Single-channel PNG of integer object ids -> [H, W] int64 (0 = unlabelled)."""
    path = Path(path)
    img = _open(path, "label map")
    if img.mode not in ("L", "P", "I", "I;16", "I;16B", "I;16L"):
        raise SceneError(path, f"label map must be a single-channel integer image, got mode {img.mode}")
    return np.array(img).astype(np.int64)


def read_mask(path: PathLike) -> np.ndarray:
    """Mask image -> [H, W] bool (nonzero = keep); RGBA masks use their alpha."""
    path = Path(path)
    img = _open(path, "mask")
    if img.mode in ("RGBA", "LA"):
        return np.array(img)[..., -1] > 0
    arr = np.array(img)
    return (arr.max(axis=-1) if arr.ndim == 3 else arr) > 0


def read_mask_values(path: PathLike) -> np.ndarray:
    """Single-channel 8/16-bit image -> [H, W] float32 in [0, 1] (soft masks, alpha)."""
    path = Path(path)
    arr = np.array(_open(path, "mask"))
    return to_float(arr if arr.ndim == 2 else arr[..., 0])


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.asarray(rgb, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def write_png(path: PathLike, array: np.ndarray) -> Path:
    """Write float images in [0, 1] as 8-bit PNG; integer arrays as 8-bit (max < 256) or 16-bit PNG. Atomic."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.asarray(array)
    if np.issubdtype(arr.dtype, np.floating):
        img = Image.fromarray(to_uint8(arr))
    elif arr.dtype == np.bool_:
        img = Image.fromarray(arr.astype(np.uint8) * 255)
    elif arr.size and (arr.min() < 0 or arr.max() > 65535):
        raise ValueError(f"{path}: integer values must lie in [0, 65535]")
    elif arr.size == 0 or arr.max() < 256:
        img = Image.fromarray(arr.astype(np.uint8))
    else:
        img = Image.fromarray(arr.astype(np.uint16))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    img.save(tmp, format="PNG")
    os.replace(tmp, path)
    return path


def list_images(folder: PathLike) -> list[Path]:
    """Image files directly inside `folder`, sorted by name (hidden files skipped)."""
    folder = Path(folder)
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix in IMAGE_EXTENSIONS and not p.name.startswith("."))


def find_sibling(folder: Path, image_name: str, extensions: tuple[str, ...]) -> Optional[Path]:
    """The file in `folder` that belongs to image `image_name`: same stem (`a.png` for `a.jpg`) or the full
    name plus an extension (`a.jpg.png`, the 3DGS mask convention); sub-folders of the name are tried first,
    then its base name alone."""
    rel = Path(image_name)
    for name in dict.fromkeys((rel, Path(rel.name))):
        for base in (name.with_suffix(""), name):
            for ext in extensions:
                cand = folder / (str(base) + ext)
                if cand.is_file():
                    return cand
    return None
