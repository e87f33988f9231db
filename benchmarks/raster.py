"""Rasterizer speed and accuracy: forward and forward+backward time, max error against the float64 reference
(on sampled pixels), Gaussian–pixel evaluation rate, and (with --gsplat, on CUDA) gsplat side by side.

What is timed is the call as a user makes it: `rasterize(...)` with its defaults (input checks on, the op's own
tile size: render/defaults.py choose_tile_size), outputs RGB + alpha + depth.

    python benchmarks/raster.py                       # CPU table: N in {1k,10k,100k} at 256x256 and 800x600
    python benchmarks/raster.py --device cuda --gsplat --sizes 100000,1000000 --resolutions 1920x1080 --rounds 3
    python benchmarks/raster.py --primitive surfels ...   # 2D surfels (gsplat: rasterization_2dgs)
    python benchmarks/raster.py --tile-sizes 8,16 ...     # one row per tile size (the image does not change)
    python benchmarks/raster.py --variants fast+bwd=warp_sums,fast+bwd=block ...
                                                          # one row per renderer variant (benchmarks/variants.py),
                                                          # timed in interleaved rounds in one process
    python benchmarks/raster.py --deterministic off,on ... # the default adjoint and the deterministic one
                                                          # (rasterize(deterministic=True)), one row each
    python benchmarks/raster.py --checks on,off --graphs on,off ...
                                                          # input checks (check_inputs) and CUDA graphs
                                                          # (warpgs.render.graph_cache) each way, one row each

Prints a table and writes benchmarks/results/raster_<device>.json (or $OUT/raster_<device>.json). With --gsplat and
--rounds > 1 each row also holds gsplat's times per round and the standard error of the per-round ratios
(ratio_fwd_se, ratio_fwd_bwd_se): a ratio within about two of them of 1.0 is a tie.
"""
from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time

import torch
import warp as wp

from common import ROOT, print_table, standard_scenes_module, sync, time_call, write_json
from variants import describe, variant

sys.path.insert(0, str(ROOT / "tests"))
from reference import render_reference  # noqa: E402  (the float64 oracles of the test suite)
from reference_surfels import render_surfels_reference  # noqa: E402

from warpgs import rasterize, rasterize_surfels  # noqa: E402

from warpgs.render import pipeline_gaussians as pipeline
from warpgs.render.surfels import surfel_work  # noqa: E402
from warpgs.render.defaults import choose_tile_size  # noqa: E402
from warpgs.render.gaussians import _intrinsics_vector  # noqa: E402
try:  # the CUDA-graph switch; older trees (before/after runs) kept it in workspace.py, or had no graphs
    from warpgs.render import graph_cache as graph_switch  # noqa: E402
except ImportError:
    from warpgs.render import workspace as graph_switch  # noqa: E402

HAS_GRAPHS = hasattr(graph_switch, "GRAPHS_ENABLED")

OUTPUTS = ("rgb", "alpha", "depth")
FLOPS_PER_EVALUATION = 20  # q (8), exp (~8 with range reduction), clamp/compare (2), blend 3 colours + depth (8) ~ 20-26


def sample_pixels(width, height, count, device, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.stack([torch.randint(0, width, (count,), generator=g), torch.randint(0, height, (count,), generator=g)],
                       -1).to(device)


def max_error_vs_reference(scene, width, height, surfels, num_pixels=128, chunk=16):
    if num_pixels == 0 or (surfels and scene[0].shape[0] > 2_000):
        return None  # the surfel oracle's distortion term is O(N^2) per pixel: too big to check here
    render, reference = (rasterize_surfels, render_surfels_reference) if surfels else (rasterize, render_reference)
    means, quats, scales, opacities, colors, viewmat, K = scene
    out = render(means, quats, scales, opacities, colors, viewmat, K, width, height, outputs=OUTPUTS)
    pix = sample_pixels(width, height, num_pixels, means.device)
    d = [t.double() for t in scene]
    err = 0.0
    for i in range(0, num_pixels, chunk):
        p = pix[i : i + chunk]
        ref = reference(*d, width, height, pixels=p)
        for name in ("rgb", "alpha"):
            ours = getattr(out, name)[p[:, 1], p[:, 0]].double()
            err = max(err, (ours - ref[name]).abs().max().item())
    return err


def evaluations(scene, width, height, tile_size):
    """Gaussian–pixel evaluations the blending loop performs (each pixel walks its tile list up to its stop)."""
    means, quats, scales, opacities, colors, viewmat, K = scene
    dev = "cpu" if means.device.type == "cpu" else "cuda:0"
    with wp.ScopedDevice(dev):
        s = pipeline.Settings(width=width, height=height, tile_size=tile_size)
        w = lambda t, dt: wp.from_torch(t.contiguous(), dtype=dt)  # noqa: E731
        proj = pipeline.project_gaussians(w(means, wp.vec3), w(quats, wp.vec4), w(scales, wp.vec3),
                                          w(opacities, wp.float32), w(colors.reshape(-1, 1, 3), wp.vec3),
                                          w(viewmat.reshape(1, 4, 4), wp.mat44),
                                          w(_intrinsics_vector(K).reshape(1, 4), wp.vec4), s, requires_grad=False)
        bins = pipeline.bin_gaussians(proj, w(opacities, wp.float32), s)
        want = pipeline.Wanted(color=True, depth=True, inv_depth=False, num_features=0)
        fwd = pipeline.blend_forward(proj, bins, w(opacities, wp.float32), wp.zeros((1, 1), dtype=float), s, want)
        last = wp.to_torch(fwd.last).view(height, width).long()
        start = wp.to_torch(bins.tile_start).long()
    ty = torch.arange(height, device=last.device) // s.tile_size
    tx = torch.arange(width, device=last.device) // s.tile_size
    tile = ty[:, None] * s.tiles_x + tx[None, :]
    walked = (last - start[tile]).clamp_min(0)
    return int(walked.sum().item()), bins.num_intersections


def single_core_gflops():
    """Measured float32 FLOP rate of one core (a large single-threaded matmul): the CPU's practical peak."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
    a @ b
    t0 = time.perf_counter()
    for _ in range(5):
        a @ b
    dt = (time.perf_counter() - t0) / 5
    torch.set_num_threads(threads)
    return 2 * 1024**3 / dt / 1e9


def gsplat_calls(scene, width, height, surfels):
    """(forward, forward+backward) of gsplat 1.5's rasterization (2dgs for surfels) on the scene, RGB+ED."""
    import gsplat

    means, quats, scales, opacities, colors, viewmat, K = scene

    def fwd(leaves=None):
        m, q, s, o, c = leaves or (means, quats, scales, opacities, colors)
        if surfels:  # gsplat takes [N,3] scales and ignores the third
            s3 = torch.cat([s, torch.zeros_like(s[:, :1])], 1)
            return gsplat.rasterization_2dgs(m, q, s3, o, c[None], viewmat[None], K[None], width, height,
                                             render_mode="RGB+ED")[0]
        img, alpha, _ = gsplat.rasterization(m, q, s, o, c, viewmat[None], K[None], width, height, packed=False,
                                             render_mode="RGB+ED")
        return img

    def fwd_bwd():
        leaves = [t.detach().requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
        fwd(leaves).sum().backward()

    return fwd, fwd_bwd


def gsplat_times(scene, width, height, device, surfels):
    fwd, fwd_bwd = gsplat_calls(scene, width, height, surfels)
    return time_call(fwd, device, warmup=3, repeats=20), time_call(fwd_bwd, device, warmup=3, repeats=20)


def warpgs_calls(scene, width, height, surfels, tile_size, check_inputs=True):
    """(forward, forward+backward) of warpgs's op on the scene (rgb, alpha, depth; loss sum of rgb and depth).
    tile_size None: the op's choice; check_inputs: the op's default."""
    render = rasterize_surfels if surfels else rasterize
    means, quats, scales, opacities, colors, viewmat, K = scene

    def fwd():
        return render(means, quats, scales, opacities, colors, viewmat, K, width, height, outputs=OUTPUTS,
                      tile_size=tile_size, check_inputs=check_inputs)

    def fwd_bwd():
        leaves = [t.detach().requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
        out = render(*leaves, viewmat, K, width, height, outputs=OUTPUTS, tile_size=tile_size,
                     check_inputs=check_inputs)
        (out.rgb.sum() + out.depth.sum()).backward()

    return fwd, fwd_bwd


def warpgs_times(scene, width, height, device, repeats, surfels, tile_size, check_inputs=True):
    fwd, fwd_bwd = warpgs_calls(scene, width, height, surfels, tile_size, check_inputs)
    warm = 3 if device.startswith("cuda") else 1
    return time_call(fwd, device, warmup=warm, repeats=repeats), time_call(fwd_bwd, device, warmup=warm, repeats=repeats)


def round_ratio_se(ours: list, theirs: list) -> float:
    """Standard error of the mean of the per-round ratios ours[r] / theirs[r]: the rounds interleave the two systems,
    so each round's pair shares the machine's state of that moment."""
    ratios = [a / b for a, b in zip(ours, theirs)]
    return statistics.stdev(ratios) / len(ratios) ** 0.5 if len(ratios) > 1 else float("nan")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", default="1000,10000,100000")
    ap.add_argument("--resolutions", default="256x256,800x600")
    ap.add_argument("--gsplat", action="store_true", help="time gsplat.rasterization side by side (CUDA)")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--error-pixels", type=int, default=128)
    ap.add_argument("--primitive", choices=["gaussians", "surfels"], default="gaussians")
    ap.add_argument("--tile-sizes", default="auto",
                    help="comma-separated tile sizes to time; auto: the op's choice (the default call)")
    ap.add_argument("--checks", default="on", help="check_inputs to time: on (the default call), off, or on,off")
    ap.add_argument("--graphs", default="on",
                    help="CUDA graphs of the launches up to the sync: on (the default), off, or on,off")
    ap.add_argument("--label", default=None, help="a tag written into every row (e.g. the commit timed)")
    ap.add_argument("--variants", default="default",
                    help="comma-separated renderer variants (benchmarks/variants.py), e.g. "
                         "fast+bwd=warp_sums,fast+bwd=block")
    ap.add_argument("--deterministic", default="off",
                    help="the blend adjoint: off (the default call), on (deterministic=True: fixed-order sums, "
                         "run-to-run identical GPU gradients), or off,on; crossed with --variants (CPU: no-op)")
    ap.add_argument("--rounds", type=int, default=1, help="interleaved timing rounds per variant (median reported)")
    ap.add_argument("--out-name", default=None, help="JSON name (default raster_<device>[_surfels])")
    args = ap.parse_args()
    scenes = standard_scenes_module()
    device = args.device
    repeats = args.repeats or (20 if device.startswith("cuda") else 3)
    peak = single_core_gflops() if device == "cpu" else None

    rows = []
    for res in args.resolutions.split(","):
        width, height = (int(v) for v in res.split("x"))
        for n in (int(v) for v in args.sizes.split(",")):
            means, quats, scales, opacities, colors, viewmat, K, W, H = scenes.random_scene(
                n, width=width, height=height, device=device)
            surfels = args.primitive == "surfels"
            if surfels:
                scales = scales[:, :2].contiguous()
            scene = (means, quats, scales, opacities, colors, viewmat, K)
            max_err = max_error_vs_reference(scene, W, H, surfels, args.error_pixels)
            for tile in (None if v == "auto" else int(v) for v in args.tile_sizes.split(",")):
                specs = [(v + ("+det=on" if d == "on" else ""), c == "on", g == "on")
                         for v in args.variants.split(",") for d in args.deterministic.split(",")
                         for c in args.checks.split(",") for g in args.graphs.split(",")]
                times = {spec: ([], []) for spec in specs + (["gsplat"] if args.gsplat else [])}
                for _ in range(args.rounds):  # interleaved, so that a busy moment hits every variant alike
                    for spec in times:
                        if spec == "gsplat":
                            f, fb = gsplat_times(scene, W, H, device, surfels)
                        else:
                            name, checks, graphs = spec
                            graph_switch.GRAPHS_ENABLED = graphs  # no such switch before graphs: then a no-op
                            with variant(name):
                                f, fb = warpgs_times(scene, W, H, device, repeats, surfels, tile, checks)
                        times[spec][0].append(f)
                        times[spec][1].append(fb)
                graph_switch.GRAPHS_ENABLED = HAS_GRAPHS
                g_times = tuple(statistics.median(v) for v in times["gsplat"]) if args.gsplat else None
                fwd_tile = choose_tile_size(tile, False, on_gpu=device.startswith("cuda"),  # the forward's
                                            primitives_per_pixel=n / (W * H), surfels=surfels)
                if surfels:
                    work = surfel_work(means, quats, scales, opacities, viewmat, K, W, H, tile_size=fwd_tile)
                    evals, pairs = work["evaluations"], work["tile_pairs"]
                else:
                    evals, pairs = evaluations(scene, W, H, fwd_tile)
                for spec in specs:
                    fwd_ms, fb_ms = (statistics.median(v) for v in times[spec])
                    with variant(spec[0]) as options:
                        name = describe()
                        deterministic = options.deterministic
                    row = dict(primitive=args.primitive, device=device, n=n, resolution=f"{W}x{H}",
                               tile_size="auto" if tile is None else tile, variant=name,
                               deterministic=deterministic, checks=spec[1],
                               graphs=spec[2] and HAS_GRAPHS and device.startswith("cuda"), fwd_ms=fwd_ms,
                               fwd_bwd_ms=fb_ms, max_err=max_err, tile_pairs=pairs, evals_per_s=evals / (fwd_ms / 1e3))
                    if args.label:
                        row["label"] = args.label
                    if args.rounds > 1:
                        row.update(fwd_ms_rounds=times[spec][0], fwd_bwd_ms_rounds=times[spec][1])
                    if peak:
                        row["frac_of_core_peak"] = row["evals_per_s"] * FLOPS_PER_EVALUATION / (peak * 1e9)
                    if g_times:
                        g_fwd, g_fb = g_times
                        row.update(gsplat_fwd_ms=g_fwd, gsplat_fwd_bwd_ms=g_fb, ratio_fwd=fwd_ms / g_fwd,
                                   ratio_fwd_bwd=fb_ms / g_fb)
                        if args.rounds > 1:
                            row.update(gsplat_fwd_ms_rounds=times["gsplat"][0],
                                       gsplat_fwd_bwd_ms_rounds=times["gsplat"][1],
                                       ratio_fwd_se=round_ratio_se(times[spec][0], times["gsplat"][0]),
                                       ratio_fwd_bwd_se=round_ratio_se(times[spec][1], times["gsplat"][1]))
                    rows.append(row)
                    print_table([row], [c for c in row if not c.endswith("_rounds")])  # progress, one row at a time
                sync(device)
    print()
    columns = ["n", "resolution", "tile_size", "variant", "deterministic", "checks", "graphs", "fwd_ms", "fwd_bwd_ms",
               "max_err", "evals_per_s"]
    columns += ["frac_of_core_peak"] if peak else []
    columns += ["gsplat_fwd_ms", "gsplat_fwd_bwd_ms", "ratio_fwd", "ratio_fwd_bwd"] if args.gsplat else []
    columns += ["ratio_fwd_se", "ratio_fwd_bwd_se"] if args.gsplat and args.rounds > 1 else []
    print_table(rows, columns)
    meta = dict(device=device, gpu=torch.cuda.get_device_name() if device.startswith("cuda") else None,
                cpu=platform.processor() or platform.machine(), torch=torch.__version__, warp=wp.__version__,
                single_core_gflops=peak, flops_per_evaluation=FLOPS_PER_EVALUATION, outputs=OUTPUTS,
                repeats=repeats, rounds=args.rounds, scenes="shared/bench/scenes.py random_scene",
                call="rasterize(...) defaults unless the row says otherwise (checks, tile_size)", label=args.label)
    suffix = "" if args.primitive == "gaussians" else "_surfels"
    path = write_json(args.out_name or f"raster_{device.split(':')[0]}{suffix}", dict(meta=meta, rows=rows))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
