"""Time each stage of the 3D rasterizer (forward and backward) on one scene, to see where time goes.

    python benchmarks/profile_stages.py --device cuda --n 1000000 --resolution 1920x1080
"""
from __future__ import annotations

import argparse
import os
import time
from contextlib import contextmanager

import torch
import warp as wp

from common import print_table, standard_scenes_module, sync
from warpgs import rasterize
from warpgs.render import pipeline_gaussians as pipeline
from warpgs.render.defaults import DEFAULT_TILE_SIZE
from warpgs.render.gaussians import _intrinsics_vector

TILE = int(os.environ.get("TILE", DEFAULT_TILE_SIZE))  # TILE=16 profiles another tile size


@contextmanager
def timed(name, device, table):
    sync(device)
    wp.synchronize()
    t0 = time.perf_counter()
    yield
    sync(device)
    wp.synchronize()
    table[name] = table.get(name, 0.0) + (time.perf_counter() - t0) * 1e3


def profile_once(scene, W, H, device):
    means, quats, scales, opacities, colors, viewmat, K = scene
    t = {}
    wdev = "cpu" if device == "cpu" else "cuda:0"
    with wp.ScopedDevice(wdev):
        s = pipeline.Settings(width=W, height=H, tile_size=TILE)
        with timed("wrap inputs", device, t):
            w = lambda x, dt: wp.from_torch(x.contiguous(), dtype=dt, requires_grad=True)  # noqa: E731
            args = (w(means, wp.vec3), w(quats, wp.vec4), w(scales, wp.vec3), w(opacities, wp.float32),
                    w(colors.reshape(-1, 1, 3), wp.vec3), wp.from_torch(viewmat.reshape(1, 4, 4).contiguous(), dtype=wp.mat44),
                    wp.from_torch(_intrinsics_vector(K).reshape(1, 4).contiguous(), dtype=wp.vec4))
        tape = wp.Tape()
        with timed("project", device, t), tape:
            proj = pipeline.project_gaussians(*args, s, requires_grad=True)
        with timed("bin+sort", device, t):
            bins = pipeline.bin_gaussians(proj, args[3], s)
        want = pipeline.Wanted(color=True, depth=True, inv_depth=False, num_features=0)
        feats = wp.zeros((1, 1), dtype=float, requires_grad=True)
        with timed("blend forward", device, t):
            fwd = pipeline.blend_forward(proj, bins, args[3], feats, s, want)
        npix = W * H
        gc = wp.full(npix, wp.vec3(1.0, 1.0, 1.0), dtype=wp.vec3)
        ga, gd = wp.zeros(npix, dtype=float), wp.ones(npix, dtype=float)
        with timed("blend backward", device, t):
            pipeline.blend_backward(proj, bins, args[3], feats, s, want, fwd, gc, ga, gd, wp.zeros(1, dtype=float),
                                    wp.zeros((1, 1), dtype=float))
        with timed("project adjoint", device, t):
            tape.backward()
    return t, bins.num_intersections


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n", type=int, default=100000)
    ap.add_argument("--resolution", default="800x600")
    args = ap.parse_args()
    W, H = (int(v) for v in args.resolution.split("x"))
    scene = standard_scenes_module().random_scene(args.n, width=W, height=H, device=args.device)[:7]
    profile_once(scene, W, H, args.device)  # compile + warm up
    runs = 5
    total = {}
    for _ in range(runs):
        t, pairs = profile_once(scene, W, H, args.device)
        for k, v in t.items():
            total[k] = total.get(k, 0.0) + v / runs
    rows = [dict(stage=k, ms=v) for k, v in total.items()]
    print(f"n={args.n} {W}x{H} on {args.device}: {pairs} Gaussian-tile pairs")
    print_table(rows, ["stage", "ms"])

    def op():
        leaves = [x.detach().requires_grad_(True) for x in scene[:5]]
        out = rasterize(*leaves, scene[5], scene[6], W, H, outputs=("rgb", "alpha", "depth"), check_inputs=False)
        (out.rgb.sum() + out.depth.sum()).backward()

    from common import time_call

    print(f"whole op forward+backward: {time_call(op, args.device, warmup=2, repeats=runs):.3f} ms")
    if args.device.startswith("cuda"):  # per-kernel GPU times of one op call (Warp's CUDA activity timing)
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        op()
        wp.timing_print(wp.timing_end())


if __name__ == "__main__":
    main()
