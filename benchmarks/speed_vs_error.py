"""Render time against error for each accuracy knob of the renderer, with the Pareto front.

Knobs swept (one at a time, the others at their defaults):
- tile_size: changes speed only (footprints are exact, so the image must not change — checked here too);
- max_sigmas: truncates each Gaussian's footprint (0 = exact alpha >= 1/255 footprint);
- sh_degree: SH bands evaluated (error against degree 3 on a degree-3 scene).
The 3DGS blending thresholds (alpha >= 1/255, stop at T < 1e-4, alpha <= 0.99) are fixed rules, not knobs.

Error is the max abs RGB error against the float64 brute-force reference (tests/reference.py) on sampled
pixels; times are medians of repeated forward and forward+backward calls.

    python benchmarks/speed_vs_error.py                        # CPU, 20k Gaussians at 320x240
    python benchmarks/speed_vs_error.py --device cuda --n 1000000 --resolution 1920x1080

Writes benchmarks/results/speed_vs_error_<device>.json and a PNG plot next to it.
"""
from __future__ import annotations

import argparse
import sys

import torch

from common import ROOT, print_table, standard_scenes_module, time_call, write_json

sys.path.insert(0, str(ROOT / "tests"))
from reference import render_reference  # noqa: E402

from warpgs import rasterize  # noqa: E402

SH_C0 = 0.28209479177387814


def degree3_scene(n, W, H, device):
    means, quats, scales, opacities, colors, viewmat, K, W, H = standard_scenes_module().random_scene(
        n, width=W, height=H, device=device)
    g = torch.Generator().manual_seed(3)
    sh = torch.zeros(n, 16, 3)
    sh[:, 0] = (colors.cpu() - 0.5) / SH_C0
    sh[:, 1:] = torch.randn(n, 15, 3, generator=g) * 0.15
    return (means, quats, scales, opacities, sh.to(device), viewmat, K), W, H


def rgb_error(scene, W, H, knobs, pixels):
    means, quats, scales, opacities, sh, viewmat, K = scene
    out = rasterize(means, quats, scales, opacities, sh, viewmat, K, W, H, outputs=("rgb",), **knobs)
    ours = out.rgb[pixels[:, 1], pixels[:, 0]].double().cpu()
    ref = []
    for i in range(0, pixels.shape[0], 16):
        r = render_reference(*(t.double() for t in scene), W, H, sh_degree=3, pixels=pixels[i : i + 16])
        ref.append(r["rgb"].cpu())
    return (ours - torch.cat(ref)).abs().max().item()


def timings(scene, W, H, knobs, device, repeats):
    means, quats, scales, opacities, sh, viewmat, K = scene

    def fwd():
        rasterize(means, quats, scales, opacities, sh, viewmat, K, W, H, outputs=("rgb",), check_inputs=False, **knobs)

    def fwd_bwd():
        leaves = [t.detach().requires_grad_(True) for t in (means, quats, scales, opacities, sh)]
        out = rasterize(*leaves, viewmat, K, W, H, outputs=("rgb",), check_inputs=False, **knobs)
        out.rgb.sum().backward()

    return time_call(fwd, device, warmup=2, repeats=repeats), time_call(fwd_bwd, device, warmup=2, repeats=repeats)


def pareto(rows):
    """Rows not beaten in both forward time and error by another row."""
    front = []
    for r in rows:
        if not any(o["fwd_ms"] <= r["fwd_ms"] and o["max_err"] <= r["max_err"] and
                   (o["fwd_ms"], o["max_err"]) != (r["fwd_ms"], r["max_err"]) for o in rows):
            front.append(r)
    return sorted(front, key=lambda r: r["fwd_ms"])


def plot(rows, front, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for knob in sorted({r["knob"] for r in rows}):
        pts = [r for r in rows if r["knob"] == knob]
        ax.scatter([p["fwd_ms"] for p in pts], [max(p["max_err"], 1e-8) for p in pts], label=knob)
        for p in pts:
            ax.annotate(str(p["value"]), (p["fwd_ms"], max(p["max_err"], 1e-8)), fontsize=7)
    ax.plot([r["fwd_ms"] for r in front], [max(r["max_err"], 1e-8) for r in front], "k--", lw=0.8, label="Pareto front")
    ax.set_xlabel("forward time (ms)")
    ax.set_ylabel("max |RGB error| vs float64 reference")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n", type=int, default=20_000)
    ap.add_argument("--resolution", default="320x240")
    ap.add_argument("--pixels", type=int, default=96)
    args = ap.parse_args()
    W, H = (int(v) for v in args.resolution.split("x"))
    scene, W, H = degree3_scene(args.n, W, H, args.device)
    g = torch.Generator().manual_seed(0)
    pixels = torch.stack([torch.randint(0, W, (args.pixels,), generator=g),
                          torch.randint(0, H, (args.pixels,), generator=g)], -1).to(args.device)
    repeats = 20 if args.device.startswith("cuda") else 3
    sweeps = [("tile_size", v, dict(tile_size=v, sh_degree=3)) for v in (8, 16, 32)]
    sweeps += [("max_sigmas", v, dict(max_sigmas=v, sh_degree=3)) for v in (1.5, 2.0, 2.5, 3.0, 0)]
    sweeps += [("sh_degree", v, dict(sh_degree=v)) for v in (0, 1, 2, 3)]
    rows = []
    for knob, value, knobs in sweeps:
        fwd_ms, fb_ms = timings(scene, W, H, knobs, args.device, repeats)
        rows.append(dict(knob=knob, value=value, fwd_ms=fwd_ms, fwd_bwd_ms=fb_ms,
                         max_err=rgb_error(scene, W, H, knobs, pixels)))
        print(f"{knob}={value}: fwd {fwd_ms:.2f} ms, fwd+bwd {fb_ms:.2f} ms, max err {rows[-1]['max_err']:.2e}")
    front = pareto(rows)
    print(f"\n{args.n} Gaussians (SH degree 3) at {W}x{H} on {args.device}")
    print_table(rows, ["knob", "value", "fwd_ms", "fwd_bwd_ms", "max_err"])
    print("Pareto front (forward time vs error): " + ", ".join(f"{r['knob']}={r['value']}" for r in front))
    path = write_json(f"speed_vs_error_{args.device.split(':')[0]}", dict(
        n=args.n, width=W, height=H, device=args.device, rows=rows, pareto=front))
    try:
        png = path.with_suffix(".png")
        plot(rows, front, png)
        print(f"wrote {path} and {png}")
    except ImportError:
        print(f"wrote {path} (install matplotlib for the plot: pip install -e '.[bench]')")


if __name__ == "__main__":
    main()
