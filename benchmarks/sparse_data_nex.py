"""LLFF scenes in NeX's layout, turned into standard LLFF folders (benchmarks/sparse_data.py `nex`).

NeX's release of the LLFF scenes re-ran COLMAP on undistorted images (~1000x750, about 1/4 of the 4032x3024
originals) and stores `poses_bounds.npy` as [N, 14]: each camera-to-world [R | c] in LLFF's axes (down, right,
back) and the near/far bounds, with the intrinsics in `hwf_cxcy.npy` ([h, w, fx, fy, cx, cy]; the principal point
is off the centre by several pixels). A standard LLFF folder has no principal point, so each image is cropped
about it (the largest window centred on (cx, cy); what is left is under half a pixel) and the poses get the
cropped [h, w, f] column: the geometry stays exact where ignoring the offset would shift every ray by ~3 px.
"""
from __future__ import annotations

import io
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from warpgs.data.formats.image_io import list_images, read_image  # noqa: E402
from warpgs.utils.atomic_file import atomic_write_bytes  # noqa: E402


def centred_window(size: int, centre: float) -> tuple[int, int]:
    """(start, stop) of the widest whole-pixel window in [0, size) whose middle is within half a pixel of
    `centre` (pixel-edge coordinates: the image spans 0..size)."""
    half = int(np.floor(min(centre, size - centre)))
    start = int(round(centre - half))
    start = min(max(start, 0), size - 2 * half)
    return start, start + 2 * half


def convert(src: Path, out: Path, jpeg_quality: int = 98) -> Path:
    """src (NeX layout: images/, poses_bounds.npy [N, 14], hwf_cxcy.npy) -> out: images/ cropped about the
    principal point and a standard [N, 17] poses_bounds.npy. Errors name the file and what was wrong."""
    from sparse_data import jpeg_bytes  # the same 4:4:4 JPEG writer as every other prepared scene

    src, out = Path(src), Path(out)
    poses_path, intr_path = src / "poses_bounds.npy", src / "hwf_cxcy.npy"
    for p in (poses_path, intr_path, src / "images"):
        if not p.exists():
            raise SystemExit(f"{p}: missing (expected NeX's layout: images/, poses_bounds.npy [N, 14], hwf_cxcy.npy)")
    pb = np.load(poses_path)
    if pb.ndim != 2 or pb.shape[1] != 14:
        raise SystemExit(f"{poses_path}: expected an [N, 14] array, got {pb.shape}")
    h, w, fx, fy, cx, cy = (float(x) for x in np.load(intr_path).ravel()[:6])
    if abs(fx - fy) > 1e-3 * fx:
        raise SystemExit(f"{intr_path}: fx {fx} and fy {fy} differ; LLFF's format has one focal length")
    files = list_images(src / "images")
    if len(files) != len(pb):
        raise SystemExit(f"{src / 'images'}: {len(files)} images for {len(pb)} poses")
    r0, r1 = centred_window(int(h), cy)
    c0, c1 = centred_window(int(w), cx)
    folder = out / "images"
    folder.mkdir(parents=True, exist_ok=True)
    for f in files:
        rgb, _ = read_image(f)
        if rgb.shape[:2] != (int(h), int(w)):
            raise SystemExit(f"{f}: {rgb.shape[1]}x{rgb.shape[0]}, hwf_cxcy.npy says {int(w)}x{int(h)}")
        atomic_write_bytes(folder / f"{f.stem}.jpg", jpeg_bytes(rgb[r0:r1, c0:c1], jpeg_quality))
    hwf = np.array([r1 - r0, c1 - c0, fx], dtype=np.float64)
    poses = np.concatenate([pb[:, :12].reshape(-1, 3, 4), np.broadcast_to(hwf[None, :, None], (len(pb), 3, 1))], 2)
    standard = np.concatenate([poses.reshape(len(pb), 15), pb[:, 12:14]], 1)
    buf = io.BytesIO()
    np.save(buf, standard)
    atomic_write_bytes(out / "poses_bounds.npy", buf.getvalue())
    print(f"{out}: {len(files)} images cropped to {c1 - c0}x{r1 - r0} about ({cx:.1f}, {cy:.1f}) "
          f"(rows {r0}:{r1}, columns {c0}:{c1})", file=sys.stderr)
    return out
