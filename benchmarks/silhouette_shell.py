"""Where a photometric fit wants a surfel shell: exact surfels on a sphere, rendered by the surfel op, against the
sphere's true pixel coverage, as the shell's radius moves (issue 32: trained surfel meshes sit inside the surface).

One sphere (radius 0.5) at the centre of the built-in orbit rig; its coverage per training view from the ray
tracer's four sub-pixel rays (what the benchmark scenes' images are made of). A shell of Fibonacci-spaced disks
tangent to a sphere of radius r, every disk of scale sigma and opacity 0.99 (the spacing is sigma / overlap, so
the shell is opaque), renders its alpha with `rasterize_surfels` at the fallback width asked. Printed per setting:
the mean |alpha - coverage| over the views for each r, the r where it is least (what a fit of the silhouette
alone moves the surface to), and the silhouette's dilation at the true radius (the surplus alpha over the
silhouette's length, in pixels).

    python benchmarks/silhouette_shell.py [--width 128] [--sigmas 0.015,0.03,0.055] [--screen 0.7071,0.3,0.1]

Writes benchmarks/results/silhouette_shell_<width>x<height>[tag].json.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import write_json  # noqa: E402

from warpgs.data.formats import raytrace  # noqa: E402
from warpgs.data.formats.synthetic import TARGET, RigSettings, orbit_rig  # noqa: E402
from warpgs.render.surfels import rasterize_surfels  # noqa: E402

RADIUS = 0.5


def true_coverage(sphere: raytrace.Sphere, cam) -> np.ndarray:
    """[H, W] share of the pixel's four sub-pixel rays that hit the sphere."""
    hits = 0.0
    for offset in raytrace.SUBPIXEL_OFFSETS:
        o, d = raytrace.camera_rays(cam, offset)
        hits = hits + np.isfinite(sphere.intersect(o, d)[0])
    return (hits / len(raytrace.SUBPIXEL_OFFSETS)).reshape(cam.height, cam.width)


def fibonacci_directions(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / n)
    azimuth = np.pi * (1.0 + 5.0 ** 0.5) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1)


def quats_facing(normals: np.ndarray) -> np.ndarray:
    """wxyz quaternions whose rotation's third column is +-normal (disks are two-sided): the shortest rotation of
    +z onto the normal flipped into the upper half, which is never the singular half-turn."""
    n = np.where(normals[:, 2:3] < 0.0, -normals, normals)
    q = np.stack([1.0 + n[:, 2], -n[:, 1], n[:, 0], np.zeros(len(n))], 1)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def shell(radius: float, sigma: float, overlap: float) -> dict:
    """Disks of scale sigma tangent to a sphere of `radius` about the rig's target, spaced sigma / overlap apart."""
    n = int(np.ceil(4.0 * np.pi * radius ** 2 / (sigma / overlap) ** 2))
    dirs = fibonacci_directions(n)
    f = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    return dict(means=f(np.asarray(TARGET) + radius * dirs), quats=f(quats_facing(dirs)),
                scales=torch.full((n, 2), float(sigma)), opacities=torch.full((n,), 0.99), colors=torch.ones(n, 3))


def alpha_errors(disks: dict, cams, coverages, screen_sigma: float) -> tuple[float, float]:
    """(mean |alpha - coverage| per pixel of the views, mean surplus alpha per view in pixels)."""
    abs_err = surplus = 0.0
    for cam, cov in zip(cams, coverages):
        out = rasterize_surfels(**disks, viewmat=torch.tensor(cam.viewmat, dtype=torch.float32),
                                K=torch.tensor(cam.K, dtype=torch.float32), width=cam.width, height=cam.height,
                                outputs=("alpha",), screen_sigma=screen_sigma)
        diff = out.alpha.reshape(cam.height, cam.width).double() - cov
        abs_err += diff.abs().mean().item()
        surplus += diff.sum().item()
    return abs_err / len(cams), surplus / len(cams)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=96)
    ap.add_argument("--sigmas", default="0.015,0.03,0.055", help="disk scales (0.055: what the benchmark trains)")
    ap.add_argument("--screen", default="0.7071,0.3,0.1", help="fallback widths in pixels (2DGS: 0.7071)")
    ap.add_argument("--overlap", type=float, default=1.0, help="disk scale over disk spacing")
    ap.add_argument("--radii", default="0.42:0.52:0.01", help="shell radii scanned, start:stop:step")
    ap.add_argument("--views", type=int, default=12, help="training views of the orbit used (evenly picked)")
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)

    cams, train, _ = orbit_rig(RigSettings(width=args.width, height=args.height))
    cams = [cams[i] for i in train][:: max(1, len(train) // args.views)][:args.views]
    sphere = raytrace.Sphere("sphere", tuple(TARGET), RADIUS, lambda p: np.ones_like(p))
    coverages = [torch.tensor(true_coverage(sphere, c)) for c in cams]
    focal = float(cams[0].K[0, 0])
    distance = float(np.linalg.norm(cams[0].center - np.asarray(TARGET)))
    perimeter_px = 2.0 * np.pi * RADIUS * focal / distance  # the silhouette's length, near enough
    start, stop, step = (float(x) for x in args.radii.split(":"))
    radii = np.round(np.arange(start, stop + 0.5 * step, step), 6)

    rows = []
    for sigma in (float(s) for s in args.sigmas.split(",")):
        for screen in (float(s) for s in args.screen.split(",")):
            scan = [(float(r), *alpha_errors(shell(r, sigma, args.overlap), cams, coverages, screen)) for r in radii]
            best = min(scan, key=lambda row: row[1])
            at_true = next((row[1:] for row in scan if row[0] == RADIUS), None) or \
                alpha_errors(shell(RADIUS, sigma, args.overlap), cams, coverages, screen)  # not in the scan
            row = {"sigma": sigma, "screen_sigma": screen, "best_radius": best[0], "offset": best[0] - RADIUS,
                   "dilation_px_at_true_radius": at_true[1] / perimeter_px,
                   "scan": [{"radius": r, "abs_error": e, "surplus_px": s} for r, e, s in scan]}
            rows.append(row)
            edge = " (at the scan's edge)" if best[0] in (radii[0], radii[-1]) else ""
            print(f"disk sigma {sigma:.3f}, fallback {screen:.3f} px: best shell radius {best[0]:.3f} "
                  f"(offset {row['offset']:+.3f}){edge}; at the true radius the silhouette is "
                  f"{row['dilation_px_at_true_radius']:+.2f} px wider", flush=True)
    footprint = distance / focal
    result = {"width": args.width, "height": args.height, "views": len(cams), "radius": RADIUS,
              "pixel_footprint_at_centre": footprint, "overlap": args.overlap, "rows": rows}
    print(f"(a pixel is {footprint:.4f} scene units at the sphere's centre)")
    print(f"-> {write_json(f'silhouette_shell_{args.width}x{args.height}{args.tag}', result)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
