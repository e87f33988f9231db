"""`warpgs-mesh`: a coloured triangle mesh (binary PLY) from a trained run.

    warpgs-mesh --model OUT [--voxel V] [--trunc T] [--depth-trunc D] [--radius R] [--center X,Y,Z] [--unbounded]
                [--out mesh.ply]

Renders depth (surfels: median depth; 3D Gaussians: expected depth, worse) and colour from the training cameras,
fuses them into a sparse TSDF volume (Warp kernels, CPU or CUDA), runs marching cubes and drops small pieces.
By default only the cube of half-size R (the training cameras' extent) around the cameras' centre is meshed;
--unbounded also meshes the background, contracted into a cube of half-size 2R.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import List, Optional

from warpgs.cli.common import EXIT_CONFIG, report_error

PROG = "warpgs-mesh"


def _error(message: str) -> int:
    return report_error(PROG, message, EXIT_CONFIG)


def _triple(text: str):
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected three numbers x,y,z, got {text!r}")
    return values


def main(argv: Optional[List[str]] = None) -> int:
    from warpgs.mesh.from_model import DEFAULT_RESOLUTION, TRUNC_VOXELS, MeshSettings

    ap = argparse.ArgumentParser(prog="warpgs-mesh", description="Mesh a trained model (TSDF fusion of its "
                                 "rendered depth, then marching cubes) into a coloured PLY.")
    ap.add_argument("--model", required=True, help="a warpgs-train output folder")
    ap.add_argument("--out", help="the PLY to write (default MODEL/mesh.ply)")
    ap.add_argument("--voxel", type=float, help=f"voxel size, world units (default 2R/{DEFAULT_RESOLUTION})")
    ap.add_argument("--trunc", type=float, help=f"TSDF truncation distance (default {TRUNC_VOXELS:g} voxels)")
    ap.add_argument("--depth-trunc", type=float, help="ignore rendered depth beyond this (default 2R; "
                                                      "none with --unbounded)")
    ap.add_argument("--radius", type=float, help="R, the half-size of the meshed cube around the cameras' centre "
                                                 "(default: the training cameras' extent)")
    ap.add_argument("--center", type=_triple, metavar="X,Y,Z",
                    help="centre of the meshed cube (default: the training cameras' mean centre)")
    ap.add_argument("--unbounded", action="store_true",
                    help="also mesh what lies outside R, contracted (coarser with distance)")
    ap.add_argument("--alpha-min", type=float, default=0.5, help="pixels less opaque carry no depth (default 0.5)")
    ap.add_argument("--min-component", type=float, default=0.01,
                    help="drop pieces with fewer faces than this fraction of the largest (default 0.01; 0 keeps all)")
    ap.add_argument("--depth", choices=("median", "expected"),
                    help="the rendered depth to fuse (default: median for surfels, expected for 3D Gaussians)")
    ap.add_argument("--device", help="cpu, cuda, cuda:1, ... (default: the run's)")
    args = ap.parse_args(argv)
    settings = MeshSettings(voxel=args.voxel, trunc=args.trunc, depth_trunc=args.depth_trunc, radius=args.radius,
                            centre=args.center, unbounded=args.unbounded, alpha_min=args.alpha_min,
                            min_component=args.min_component, depth=args.depth)
    try:
        settings.check()
    except ValueError as e:
        return _error(str(e))
    run = Path(args.model)
    if not run.is_dir():
        return _error(f"--model: {run} is not a folder (expected a warpgs-train output folder)")
    out = Path(args.out) if args.out else run / "mesh.ply"
    if out.suffix.lower() != ".ply":
        return _error(f"--out: {out} should end in .ply (a binary PLY mesh is written)")

    from warpgs.cli.commands import load_run
    from warpgs.mesh.from_model import mesh_trainer
    from warpgs.mesh.ply_mesh import write_mesh_ply

    t0 = time.perf_counter()
    try:
        trainer = load_run(run, args.device)
    except (ValueError, FileNotFoundError) as e:
        return _error(str(e))
    kind = trainer.model.kind
    if kind != "surfels":
        print("warpgs-mesh: note: 3D Gaussians have no sharp depth; meshing their expected depth gives a rougher, "
              "less complete mesh than surfels (model.kind=surfels) would", file=sys.stderr)
    try:
        mesh = mesh_trainer(trainer, settings, args.device, report=lambda s: print(s, file=sys.stderr))
    except ValueError as e:
        return _error(str(e))
    if len(mesh.faces) == 0:
        return _error("no surface found: no voxel was seen from both sides of a depth sample; try a larger "
                      "--voxel or --depth-trunc, or --unbounded")
    t = settings.timings
    try:
        write_mesh_ply(out, mesh, comment=f"warpgs-mesh of {run.name}: {kind}, {t['depth']}, voxel {t['voxel']:.6g}")
    except OSError as e:  # e.g. a file where a folder of the path should be, no permission, a full disk
        return _error(f"--out: cannot write {out}: {e}")
    print(f"mesh: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces from {t['views']} views of "
          f"{trainer.model.num_primitives} {kind} (voxel {t['voxel']:.4g}, trunc {t['trunc']:.4g}, "
          f"radius {t['radius']:.4g}{', unbounded' if settings.unbounded else ''}); render {t['render_s']:.1f} s, "
          f"fusion {t['fusion_s']:.1f} s, marching cubes {t['marching_cubes_s']:.1f} s, "
          f"total {time.perf_counter() - t0:.1f} s -> {out.resolve()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
