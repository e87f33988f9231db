"""Time each stage of the 3D (or surfel) rasterizer, forward and backward, on one scene, to see where time goes,
for one or several renderer variants side by side (benchmarks/variants.py).

    python benchmarks/profile_stages.py --device cuda --n 1000000 --resolution 1920x1080
    python benchmarks/profile_stages.py --device cuda --variants fast+bwd=warp_sums,fast+bwd=block
    python benchmarks/profile_stages.py --device cuda --primitive surfels --variants fast+sbwd=block,fast+sbwd=warp_sums

Variants are timed through the real op (forward and backward through autograd) with a synchronisation after each
stage (tile_binning.stage_hook); surfels drop the scene's third scale. Stage times include the host work of the
stage. Then the whole op, forward and forward+backward, without the hooks, and
on CUDA the per-kernel GPU times of one call (Warp's activity timing; the radix sorts are CUB calls it may not see).
Prints tables and writes benchmarks/results/profile_stages_<device>.json ($OUT when set).
"""
from __future__ import annotations

import argparse
import os
import time

import torch
import warp as wp

from common import print_table, standard_scenes_module, sync, time_call, write_json
from variants import describe, variant
from warpgs import rasterize, rasterize_surfels
from warpgs.render import tile_binning
from warpgs.render.defaults import DEFAULT_TILE_SIZE

OUTPUTS = ("rgb", "alpha", "depth")


class StageClock:
    """The fast pipeline's stage hook: synchronises and charges the time since the last mark to the stage."""

    def __init__(self, device):
        self.device = device
        self.table = {}
        self.mark()

    def mark(self):
        sync(self.device)
        wp.synchronize()
        self.t0 = time.perf_counter()

    def __call__(self, name):
        sync(self.device)
        wp.synchronize()
        t = time.perf_counter()
        self.table[name] = self.table.get(name, 0.0) + (t - self.t0) * 1e3
        self.t0 = t


def profile_fast(scene, W, H, device, tile, render=rasterize):
    means, quats, scales, opacities, colors, viewmat, K = scene
    leaves = [x.detach().requires_grad_(True) for x in (means, quats, scales, opacities, colors)]
    clock = StageClock(device)
    tile_binning.stage_hook = clock
    try:
        clock.mark()
        out = render(*leaves, viewmat, K, W, H, outputs=OUTPUTS, tile_size=tile, check_inputs=False)
        (out.rgb.sum() + out.depth.sum()).backward()
        clock("end (grads to autograd)")
    finally:
        tile_binning.stage_hook = None
    return clock.table, out.num_intersections


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n", type=int, default=100000)
    ap.add_argument("--resolution", default="800x600")
    ap.add_argument("--tile", type=int, default=int(os.environ.get("TILE", DEFAULT_TILE_SIZE)))
    ap.add_argument("--variants", default="default", help="comma-separated (benchmarks/variants.py)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--kernel-timing", action="store_true", help="CUDA: also print Warp's per-kernel GPU times")
    ap.add_argument("--primitive", choices=["gaussians", "surfels"], default="gaussians")
    ap.add_argument("--out-name", default=None)
    args = ap.parse_args()
    W, H = (int(v) for v in args.resolution.split("x"))
    scene = list(standard_scenes_module().random_scene(args.n, width=W, height=H, device=args.device)[:7])
    surfels = args.primitive == "surfels"
    render = rasterize_surfels if surfels else rasterize
    if surfels:
        scene[2] = scene[2][:, :2].contiguous()  # a surfel's two disk axes
    specs = args.variants.split(",")
    stage_rows, op_rows, pairs = [], [], None
    for spec in specs:
        with variant(spec):
            name = describe()
            profile_fast(scene, W, H, args.device, args.tile, render)  # compile + warm up
            total = {}
            for _ in range(args.runs):
                t, pairs = profile_fast(scene, W, H, args.device, args.tile, render)
                for k, v in t.items():
                    total[k] = total.get(k, 0.0) + v / args.runs
            stage_rows += [dict(variant=name, stage=k, ms=v) for k, v in total.items()]

            means, quats, scales, opacities, colors, viewmat, K = scene

            def fwd():
                return render(means, quats, scales, opacities, colors, viewmat, K, W, H, outputs=OUTPUTS,
                              tile_size=args.tile, check_inputs=False)

            def fwd_bwd():
                leaves = [x.detach().requires_grad_(True) for x in scene[:5]]
                out = render(*leaves, viewmat, K, W, H, outputs=OUTPUTS, tile_size=args.tile, check_inputs=False)
                (out.rgb.sum() + out.depth.sum()).backward()

            op_rows.append(dict(variant=name, fwd_ms=time_call(fwd, args.device, 2, args.runs),
                                fwd_bwd_ms=time_call(fwd_bwd, args.device, 2, args.runs)))
            if args.kernel_timing and args.device.startswith("cuda"):
                print(f"--- per-kernel GPU times, {name}: one forward+backward")
                wp.timing_begin(cuda_filter=wp.TIMING_ALL)
                fwd_bwd()
                wp.timing_print(wp.timing_end())
    print(f"{args.primitive} n={args.n} {W}x{H} tile {args.tile} on {args.device}: {pairs} primitive-tile pairs; "
          f"stage times with a sync after each stage (mean of {args.runs})")
    print_table(stage_rows, ["variant", "stage", "ms"])
    print("\nwhole op, no stage syncs (median):")
    print_table(op_rows, ["variant", "fwd_ms", "fwd_bwd_ms"])
    meta = dict(device=args.device, gpu=torch.cuda.get_device_name() if args.device.startswith("cuda") else None,
                primitive=args.primitive, n=args.n, resolution=f"{W}x{H}", tile_size=args.tile, tile_pairs=pairs,
                runs=args.runs, torch=torch.__version__, warp=wp.__version__)
    path = write_json(args.out_name or f"profile_stages_{args.device.split(':')[0]}{'_surfels' if surfels else ''}",
                      dict(meta=meta, stages=stage_rows, op=op_rows))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
