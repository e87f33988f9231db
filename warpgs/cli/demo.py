"""`warpgs-demo`: render a small procedural Gaussian scene (a torus over a checkered floor) to PNG files.

A smoke test of an installation: it exercises projection, SH colour, tiling, blending and the depth output
on whichever device is available, and prints where the images went.
"""
from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from warpgs.render.gaussians import rasterize


def torus_and_floor(n_torus: int = 6000, n_floor: int = 4000, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n_torus, generator=g) * 2 * math.pi
    v = torch.rand(n_torus, generator=g) * 2 * math.pi
    R, r = 1.0, 0.35
    torus = torch.stack([(R + r * torch.cos(v)) * torch.cos(u), -0.6 - r * torch.sin(v), (R + r * torch.cos(v)) * torch.sin(u)], -1)
    torus_rgb = torch.stack([0.5 + 0.5 * torch.cos(u), 0.5 + 0.5 * torch.sin(v), 0.6 + 0.0 * u], -1)
    xz = (torch.rand(n_floor, 2, generator=g) - 0.5) * 5
    floor = torch.stack([xz[:, 0], torch.zeros(n_floor), xz[:, 1]], -1)
    checker = ((torch.floor(xz[:, 0] * 2) + torch.floor(xz[:, 1] * 2)) % 2)[:, None]
    floor_rgb = 0.25 + 0.5 * checker.expand(-1, 3)
    means = torch.cat([torus, floor])
    rgb = torch.cat([torus_rgb, floor_rgb])
    n = means.shape[0]
    scales = torch.cat([torch.full((n_torus, 3), 0.045), torch.tensor([0.07, 0.01, 0.07]).expand(n_floor, 3)])
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).contiguous()
    opacities = torch.full((n,), 0.85)
    sh = torch.zeros(n, 4, 3)
    sh[:, 0] = (rgb - 0.5) / 0.28209479177387814  # degree-0 band reproduces rgb exactly
    sh[:, 1:] = torch.randn(n, 3, 3, generator=g) * 0.05  # a little view dependence
    return means, quats, scales, opacities, sh


def orbit_camera(angle: float, radius: float = 4.0, height: float = -1.6):
    eye = torch.tensor([radius * math.sin(angle), height, -radius * math.cos(angle)])
    forward = -eye / eye.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0]), forward)
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    R = torch.stack([right, down, forward])
    view = torch.eye(4)
    view[:3, :3] = R
    view[:3, 3] = -R @ eye
    return view


def save_png(path: Path, image: torch.Tensor) -> None:
    from PIL import Image

    arr = (image.detach().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
    tmp = path.with_name(path.stem + ".tmp.png")
    Image.fromarray(arr.squeeze(-1) if arr.shape[-1] == 1 else arr).save(tmp)
    os.replace(tmp, path)  # never leave a half-written image behind


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="warpgs-demo", help="output folder (default: ./warpgs-demo)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--views", type=int, default=4)
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    means, quats, scales, opacities, sh = (t.to(args.device) for t in torus_and_floor())
    f = 0.9 * args.width
    K = torch.tensor([[f, 0, args.width / 2], [0, f, args.height / 2], [0, 0, 1.0]], device=args.device)
    t0 = time.perf_counter()
    for i in range(args.views):
        view = orbit_camera(2 * math.pi * i / args.views).to(args.device)
        r = rasterize(means, quats, scales, opacities, sh, view, K, args.width, args.height, sh_degree=1,
                      background=torch.ones(3, device=args.device), outputs=("rgb", "alpha", "depth"))
        depth = r.depth / r.depth[r.alpha > 0.5].max().clamp_min(1e-6)
        save_png(out / f"view{i:02d}_rgb.png", r.rgb)
        save_png(out / f"view{i:02d}_depth.png", 1.0 - depth.clamp(0, 1))
    dt = time.perf_counter() - t0
    print(f"rendered {args.views} views of {means.shape[0]} Gaussians at {args.width}x{args.height} on "
          f"{args.device} in {dt:.2f} s; images in {out.resolve()}")


if __name__ == "__main__":
    main()
