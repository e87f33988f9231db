"""Memory of the preloaded training views, as the trainer keeps them, and the cost of drawing one: 8-bit images kept
as their codes (the default, data/compact_image.py) against float32 (every image kept as loaded).

    python benchmarks/view_memory.py data/phone64 --device cuda --downscale 1

Both ways load the capture's training views (its LLFF split) from a fresh scene into a fresh TrainViews and report the
images' bytes, the device memory the loaded views hold (torch's allocator, CUDA only), the load time (decoding and,
for the codes, the exactness check) and the median time of drawing a view (the codes expanded to float32; nothing
to do for float32). Writes benchmarks/results/view_memory_<name>_<device>.json.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from unittest import mock

import torch

from common import ROOT, print_table, run_host, sync, write_json

sys.path.insert(0, str(ROOT))

from warpgs.data import compact_image, load_scene  # noqa: E402
from warpgs.train.views import TrainViews  # noqa: E402


def measure(scene, device: str, draws: int) -> dict:
    """Load every training view into a fresh TrainViews; its kept bytes, device memory and draw time."""
    dev = torch.device(device)
    cuda = dev.type == "cuda"
    if cuda:
        torch.cuda.empty_cache()
        before = torch.cuda.memory_allocated(dev)
    views = TrainViews(scene, device, seed=0)
    t0 = time.perf_counter()
    views.load_all()
    sync(device)
    load_s = time.perf_counter() - t0
    held = torch.cuda.memory_allocated(dev) - before if cuda else None
    order = views.draw(draws)
    times = []
    for i in order:
        sync(device)
        t0 = time.perf_counter()
        image = views.view(i).image
        sync(device)
        times.append((time.perf_counter() - t0) * 1e3)
        del image
    row = {"image_bytes": views.kept_bytes(), "device_bytes": held, "load_s": round(load_s, 3),
           "draw_ms": round(statistics.median(times), 4)}
    del views
    return row


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", help="scene folder")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--downscale", type=int, default=1)
    ap.add_argument("--draws", type=int, default=50, help="views drawn for the draw time")
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)

    def fresh():  # a new scene each time: none of the images already decoded in its memory
        return load_scene(args.data, split="llff", downscale=args.downscale)

    scene = fresh()
    for i in scene.train:  # resized copies into the disk cache first, so both ways read the same files
        scene.image_np(i)
    rows = []
    for name in ("8-bit codes", "float32"):
        if name == "float32":
            with mock.patch.object(compact_image, "pack", lambda image: None):
                row = measure(fresh(), args.device, args.draws)
        else:
            row = measure(fresh(), args.device, args.draws)
        rows.append({"kept as": name, **row})
    views = len(scene.train)
    h, w = scene.cameras[scene.train[0]].height, scene.cameras[scene.train[0]].width
    print(f"{Path(args.data).name}: {views} training views at {w}x{h}, {args.device}")
    print_table(rows, ["kept as", "image_bytes", "device_bytes", "load_s", "draw_ms"])
    name = f"view_memory_{Path(args.data).name}_{args.device.split(':')[0]}" + (f"_{args.tag}" if args.tag else "")
    payload = {"data": str(args.data), "device": args.device, "downscale": args.downscale, "views": views,
               "size": [w, h], "rows": rows, "host": run_host(args.device)}
    print(f"wrote {write_json(name, payload)}")
    return payload


if __name__ == "__main__":
    main()
