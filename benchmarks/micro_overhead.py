"""Per-call host overhead of the pieces a render call is made of: kernel launches (fresh and replayed), array
wrapping, allocations and zero-fills. The GPU kernels at 100k Gaussians take tens of microseconds, so these
host costs are what a small render spends its time on.

    python benchmarks/micro_overhead.py [--device cuda]

Prints microseconds per operation and writes benchmarks/results/micro_overhead_<device>.json ($OUT when set).
The last rows are whole render calls of one Gaussian and of one surfel on an 8x8 image: the fixed cost every
render pays (on the CPU set WARPGS_CPU_THREADS=1, or the thread pool's hand-off
dominates).
"""
from __future__ import annotations

import argparse
import time

import torch
import warp as wp

from common import print_table, sync, write_json

from warpgs.kernels import blend, binning
from warpgs.render import pipeline_gaussians as pipeline


def per_call_us(fn, device, repeats=2000):
    for _ in range(20):
        fn()
    sync(device)
    wp.synchronize()
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    sync(device)
    wp.synchronize()
    return (time.perf_counter() - t0) / repeats * 1e6


def whole_op_rows(device):
    """The fixed cost of one render call: one primitive (a 3D Gaussian, a surfel), an 8x8 image (nearly no kernel
    work)."""
    from warpgs import rasterize, rasterize_surfels

    g = torch.Generator().manual_seed(0)
    means = torch.tensor([[0.0, 0.0, 4.0]], device=device)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=device)
    opacities = torch.full((1,), 0.8, device=device)
    colors = torch.rand(1, 3, generator=g).to(device)
    viewmat = torch.eye(4, device=device)
    K = torch.tensor([[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]], device=device)
    rows = []
    for kind, render, dims in (("Gaussian", rasterize, 3), ("surfel", rasterize_surfels, 2)):
        scales = torch.full((1, dims), 0.2, device=device)

        def fwd():
            render(means, quats, scales, opacities, colors, viewmat, K, 8, 8, outputs=("rgb", "alpha", "depth"),
                   tile_size=8, check_inputs=False)

        def fwd_bwd():
            leaves = [t.detach().requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
            out = render(*leaves, viewmat, K, 8, 8, outputs=("rgb", "alpha", "depth"), tile_size=8,
                         check_inputs=False)
            (out.rgb.sum() + out.depth.sum()).backward()

        for name, fn in (("forward", fwd), ("forward+backward", fwd_bwd)):
            rows.append(dict(operation=f"{render.__name__} {name}, 1 {kind}, 8x8",
                             us=min(per_call_us(fn, device, 200) for _ in range(3))))
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n", type=int, default=100_000, help="array size for allocations and zero-fills")
    args = ap.parse_args()
    device = args.device
    wdev = "cpu" if device == "cpu" else "cuda:0"
    n = args.n
    rows = []
    with wp.ScopedDevice(wdev):
        s = pipeline.Settings(width=1, height=0, tile_size=8)  # an image of no rows: the kernel returns at once
        want = pipeline.Wanted(color=True, depth=True, inv_depth=False, num_features=0)
        one = lambda dt: wp.zeros(1, dtype=dt)  # noqa: E731
        feats = wp.zeros((1, 1), dtype=float)
        bwd_args = ([one(wp.int32), one(wp.int32), one(wp.vec2), one(wp.vec3), one(float), one(wp.vec3), one(float),
                     feats, one(float), pipeline.blend_params(s, want)]
                    + [one(float), one(wp.int32), one(float), one(wp.vec3), one(float), one(float), one(float), feats]
                    + [one(wp.vec2), one(wp.vec3), one(float), one(wp.vec3), one(float), feats])
        small_args = [one(wp.int32), one(wp.int32), one(wp.int32)]

        def launch_23():
            wp.launch(blend.blend_backward, dim=1, inputs=bwd_args)

        def launch_3():
            wp.launch(binning.depth_sort_keys, dim=1, inputs=small_args)

        cmd23 = wp.launch(blend.blend_backward, dim=1, inputs=bwd_args, record_cmd=True)
        cmd3 = wp.launch(binning.depth_sort_keys, dim=1, inputs=small_args, record_cmd=True)
        fresh = one(wp.vec2)

        def set_one_array():
            cmd23.set_param_at_index(2, fresh)

        def set_dim():
            cmd23.set_dim(1)

        def scoped_device():
            with wp.ScopedDevice(wdev):
                pass

        t = torch.zeros(n, 3, device=device)
        g = torch.zeros(n, 3, device=device)
        ops = {
            "wp.launch, 23 arguments": launch_23,
            "wp.launch, 3 arguments": launch_3,
            "Launch.launch() replay, 23 arguments": cmd23.launch,
            "Launch.launch() replay, 3 arguments": cmd3.launch,
            "Launch.set_param_at_index (one array)": set_one_array,
            "Launch.set_dim": set_dim,
            "blend_params struct": lambda: pipeline.blend_params(s, want),
            "wp.from_torch vec3": lambda: wp.from_torch(t, dtype=wp.vec3),
            "wp.from_torch vec3 + grad": lambda: wp.from_torch(t, dtype=wp.vec3, grad=g),
            "wp.from_torch return_ctype": lambda: wp.from_torch(t, dtype=wp.vec3, return_ctype=True),
            "wp.to_torch": lambda: wp.to_torch(fresh),
            "wp.array(ptr=...) view": lambda: wp.array(ptr=t.data_ptr(), dtype=wp.vec3, shape=(n,), device=wdev),
            f"wp.empty({n}, vec3)": lambda: wp.empty(n, dtype=wp.vec3),
            f"wp.zeros({n}, vec3)": lambda: wp.zeros(n, dtype=wp.vec3),
            f"wp.zeros({n}, vec3, requires_grad)": lambda: wp.zeros(n, dtype=wp.vec3, requires_grad=True),
            f"torch.empty({n}, 3)": lambda: torch.empty(n, 3, device=device),
            f"torch.zeros({n}, 3)": lambda: torch.zeros(n, 3, device=device),
            "wp.ScopedDevice enter/exit": scoped_device,
        }
        for name, fn in ops.items():
            reps = 200 if "zeros" in name and device == "cpu" else 2000
            rows.append(dict(operation=name, us=per_call_us(fn, device, reps)))
    rows += whole_op_rows(device)
    print_table(rows, ["operation", "us"])
    path = write_json(f"micro_overhead_{device.split(':')[0]}", dict(device=device, warp=wp.__version__, n=n,
                                                                      rows=rows))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
