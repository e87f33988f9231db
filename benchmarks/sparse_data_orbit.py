"""Photos of a walk-around capture made ready for SfM and the 360° protocols (benchmarks/sparse_data.py `orbit`).

The protocols split a capture in name order (every 8th view tests, the training views spread over the rest), which
follows the walk only when the names sort in capture order: `1.jpg, 2.jpg, ..., 10.jpg` sorts 1, 10, 11, ..., 2, so
each photo is renamed after the last number in its name, zero-padded (`0001.jpg`). Phone photos and video frames
are also larger than the protocols read (FSGS's ~500-800 px): `--factor` area-averages them first, which also
keeps SfM and the carried copy small."""
from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from warpgs.data.formats.image_io import list_images, read_image  # noqa: E402
from warpgs.data.formats.resize import resize_area  # noqa: E402
from warpgs.utils.atomic_file import atomic_write_bytes  # noqa: E402


def numbered_name(path: Path, digits: int = 4) -> str:
    """`<last number in the stem, zero-padded to digits>.jpg`; a name without a number is an error naming it."""
    numbers = re.findall(r"\d+", Path(path).stem)
    if not numbers:
        raise SystemExit(f"{path}: no number in the file name, so its place in the capture is unknown")
    return f"{int(numbers[-1]):0{digits}d}.jpg"


def orbit_images(src: Path, dest: Path, factor: int = 1, quality: int = 95) -> list[Path]:
    """Every image in src as dest/<numbered_name>.jpg at 1/factor of its size (area-averaged, JPEG of `quality`).
    Two images with one number are an error naming both."""
    from sparse_data import jpeg_bytes

    if factor < 1:
        raise SystemExit(f"--factor: expected a whole number >= 1, got {factor}")
    files = list_images(Path(src))
    if not files:
        raise SystemExit(f"{src}: no images")
    names: dict = {}
    for f in files:
        name = numbered_name(f)
        if name in names:
            raise SystemExit(f"{f} and {names[name]}: two images numbered {name}")
        names[name] = f
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    for name, f in sorted(names.items()):
        rgb, _ = read_image(f)
        if factor > 1:
            rgb = resize_area(rgb, rgb.shape[1] // factor, rgb.shape[0] // factor)
        atomic_write_bytes(dest / name, jpeg_bytes(rgb, quality))
    return [dest / n for n in sorted(names)]
