"""Render speed along a moving camera (a viewer, an evaluation pass): the default `rasterize(...)` call on a path of
views that each change the tile-pair count a little, where `benchmarks/raster.py` repeats one view. Forward only
(no gradient, as a viewer renders) and forward+backward; renderer variants (benchmarks/variants.py) and, with
--gsplat on CUDA, gsplat's rasterization on the same views, interleaved in rounds in one process.

    python benchmarks/raster_views.py --device cuda --gsplat --sizes 100000,1000000 --variants fast,fast+psort=padded

Each round renders the path twice per system and times the second pass (the first lets each system settle: caches,
CUDA graphs); a round's figure is the median ms per view. Prints a table and writes
benchmarks/results/raster_views_<device>.json (or $OUT/...), with every round's figures and the standard error of the
per-round ratios to the first variant (and to gsplat).
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from common import print_table, standard_scenes_module, sync, write_json
from raster import gsplat_calls, round_ratio_se, warpgs_calls
from variants import describe, variant
from warpgs.render.device_state import device_state


def camera_path(viewmat: torch.Tensor, count: int, step: float = 0.02) -> list:
    """`count` world-to-camera matrices sliding sideways across `viewmat` (step per view in x, a small zig-zag in y):
    neighbouring views see nearly the same Gaussians, so their pair counts differ by a few percent."""
    views = []
    for i in range(count):
        v = viewmat.clone()
        v[0, 3] += step * (i - count // 2)
        v[1, 3] += 0.5 * step * ((i * 7) % 11 - 5)
        views.append(v)
    return views


def warpgs_view(scene, width, height, backward: bool):
    """One view's render as raster.py times it (its warpgs_calls, with the view's matrix)."""
    def render(viewmat):
        fwd, fwd_bwd = warpgs_calls(scene[:5] + (viewmat, scene[6]), width, height, False, None)
        return (fwd_bwd if backward else fwd)()

    return render


def gsplat_view(scene, width, height, backward: bool):
    def render(viewmat):
        fwd, fwd_bwd = gsplat_calls(scene[:5] + (viewmat, scene[6]), width, height, False)
        (fwd_bwd if backward else fwd)()

    return render


def ms_per_view(render, views, device: str) -> float:
    """Median ms per view of the second of two passes over `views`, each call synchronised."""
    for _ in range(2):
        times = []
        for v in views:
            sync(device)
            t0 = time.perf_counter()
            render(v)
            sync(device)
            times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--sizes", default="100000,1000000")
    ap.add_argument("--resolution", default="1920x1080")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--variants", default="fast", help="comma-separated renderer variants (benchmarks/variants.py)")
    ap.add_argument("--gsplat", action="store_true", help="gsplat.rasterization on the same views (CUDA)")
    ap.add_argument("--out-name", default=None, help="JSON name (default raster_views_<device>)")
    args = ap.parse_args(argv)
    scenes = standard_scenes_module()
    width, height = (int(v) for v in args.resolution.split("x"))
    specs = args.variants.split(",")
    rows = []
    for n in (int(v) for v in args.sizes.split(",")):
        scene = scenes.random_scene(n, width=width, height=height, device=args.device)[:7]
        views = camera_path(scene[5], args.views)
        for backward in (False, True):
            mode = "fwd_bwd" if backward else "fwd"
            times = {s: [] for s in specs + (["gsplat"] if args.gsplat else [])}
            for _ in range(args.rounds):
                for spec in times:
                    if spec == "gsplat":
                        times[spec].append(ms_per_view(gsplat_view(scene, width, height, backward), views,
                                                       args.device))
                        continue
                    with variant(spec):
                        times[spec].append(ms_per_view(warpgs_view(scene, width, height, backward), views,
                                                       args.device))
            first = times[specs[0]]
            for spec in specs:
                with variant(spec):
                    name = describe()
                row = dict(n=n, resolution=args.resolution, views=args.views, mode=mode, variant=name,
                           ms_per_view=statistics.median(times[spec]), ms_rounds=times[spec],
                           ratio_to_first=statistics.median(times[spec]) / statistics.median(first),
                           ratio_to_first_se=round_ratio_se(times[spec], first))
                if args.gsplat:
                    row.update(gsplat_ms_per_view=statistics.median(times["gsplat"]), gsplat_ms_rounds=times["gsplat"],
                               ratio_gsplat=row["ms_per_view"] / statistics.median(times["gsplat"]),
                               ratio_gsplat_se=round_ratio_se(times[spec], times["gsplat"]))
                rows.append(row)
    columns = ["n", "mode", "variant", "ms_per_view", "ratio_to_first", "ratio_to_first_se"]
    columns += ["gsplat_ms_per_view", "ratio_gsplat", "ratio_gsplat_se"] if args.gsplat else []
    print_table(rows, columns)
    meta = dict(device=args.device, gpu=torch.cuda.get_device_name() if args.device.startswith("cuda") else None,
                rounds=args.rounds, scenes="shared/bench/scenes.py random_scene", path="raster_views.camera_path",
                call="rasterize(...) defaults, outputs rgb, alpha, depth",
                # forward-only renders sorted ahead of their count, and those of them sorted again (pair_sort "ahead")
                pair_rooms=device_state(torch.device(args.device)).ws.pair_rooms.stats())
    path = write_json(args.out_name or f"raster_views_{args.device.split(':')[0]}", dict(meta=meta, rows=rows))
    print(f"wrote {path}")
    return rows


if __name__ == "__main__":
    main()
