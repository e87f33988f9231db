"""Render time against error for each accuracy knob of the renderer, and against held-out PSNR after a fixed
training budget, with the Pareto fronts.

Knobs swept (one at a time, the others at their defaults, which are the 3DGS rules):
- tile_size: changes speed only (footprints are exact, so the image must not change — checked here too);
- max_sigmas: truncates each Gaussian's footprint (0 = exact alpha >= alpha_min footprint);
- alpha_min: contributions below this alpha are skipped (3DGS: 1/255); also shrinks the footprints;
- transmittance_min: a pixel stops blending before its transmittance drops under this (3DGS: 1e-4);
- sh_degree: SH bands evaluated (error against degree 3 on a degree-3 scene).
Parameters are stored and rendered in float32 only, so there is no precision knob to sweep.

Render error is the max abs RGB error against the float64 brute-force reference (tests/reference.py, run at the
default thresholds: the exact 3DGS image) on sampled pixels. Times are taken on a standard random scene
(../shared/bench/scenes.py) in --rounds interleaved rounds (every setting once per round, so drift of the
machine hits all settings alike); a setting's time is the median over rounds of the median of repeated
calls, and fwd_spread is (max - min) / median of its per-round forward times: differences below that are noise.
Training (--train-steps > 0): for each setting, `configs/default.yaml` (the built-in synthetic orbit scene) is
trained for that many steps with the knob set in the trainer (train.<knob>, model.sh_degree), and the held-out
PSNR and training wall time are recorded. Settings with the same effective configuration are trained once.

    python benchmarks/speed_vs_error.py                        # CPU: 20k Gaussians at 320x240, 300 training steps
    python benchmarks/speed_vs_error.py --device cuda --n 200000 --resolution 1920x1080 --train-steps 2000

Writes benchmarks/results/speed_vs_error_<device>.json and a PNG plot next to it.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

from common import ROOT, print_table, standard_scenes_module, time_call, write_json

sys.path.insert(0, str(ROOT / "tests"))
from reference import render_reference  # noqa: E402

from warpgs import rasterize  # noqa: E402
from warpgs.render.defaults import DEFAULT_ALPHA_MIN, DEFAULT_TILE_SIZE, DEFAULT_TRANSMITTANCE_MIN  # noqa: E402

SH_C0 = 0.28209479177387814
DEFAULTS = dict(tile_size=DEFAULT_TILE_SIZE, max_sigmas=0.0, alpha_min=DEFAULT_ALPHA_MIN,
                transmittance_min=DEFAULT_TRANSMITTANCE_MIN, sh_degree=3)
SWEEPS = {
    "tile_size": (8, 16, 32),
    "max_sigmas": (1.5, 2.0, 2.5, 3.0, 0.0),
    "alpha_min": (1.0 / 255.0, 0.01, 0.02, 0.05, 0.08),  # below model.init_opacity (0.1), as the trainer requires
    "transmittance_min": (1.0e-4, 1.0e-3, 1.0e-2, 0.05),
    "sh_degree": (0, 1, 2, 3),
}


def degree3_scene(n, W, H, device):
    means, quats, scales, opacities, colors, viewmat, K, W, H = standard_scenes_module().random_scene(
        n, width=W, height=H, device=device)
    g = torch.Generator().manual_seed(3)
    sh = torch.zeros(n, 16, 3)
    sh[:, 0] = (colors.cpu() - 0.5) / SH_C0
    sh[:, 1:] = torch.randn(n, 15, 3, generator=g) * 0.15
    return (means, quats, scales, opacities, sh.to(device), viewmat, K), W, H


def reference_rgb(scene, W, H, pixels):
    """The exact 3DGS image (default thresholds, SH degree 3) at the sampled pixels, in float64."""
    ref = []
    for i in range(0, pixels.shape[0], 16):
        r = render_reference(*(t.double() for t in scene), W, H, sh_degree=3, pixels=pixels[i : i + 16])
        ref.append(r["rgb"].cpu())
    return torch.cat(ref)


def rgb_error(scene, W, H, knobs, pixels, ref):
    means, quats, scales, opacities, sh, viewmat, K = scene
    out = rasterize(means, quats, scales, opacities, sh, viewmat, K, W, H, outputs=("rgb",), **knobs)
    return (out.rgb[pixels[:, 1], pixels[:, 0]].double().cpu() - ref).abs().max().item()


def timings(scene, W, H, knobs, device, repeats):
    means, quats, scales, opacities, sh, viewmat, K = scene

    def fwd():
        rasterize(means, quats, scales, opacities, sh, viewmat, K, W, H, outputs=("rgb",), check_inputs=False, **knobs)

    def fwd_bwd():
        leaves = [t.detach().requires_grad_(True) for t in (means, quats, scales, opacities, sh)]
        out = rasterize(*leaves, viewmat, K, W, H, outputs=("rgb",), check_inputs=False, **knobs)
        out.rgb.sum().backward()

    return time_call(fwd, device, warmup=2, repeats=repeats), time_call(fwd_bwd, device, warmup=2, repeats=repeats)


def train_psnr(knobs: dict, steps: int, device: str, workdir: Path) -> dict:
    """Held-out PSNR of configs/default.yaml trained `steps` steps with the renderer knobs set in the trainer."""
    from warpgs.config.loader import load_config
    from warpgs.train.trainer import Trainer

    overrides = [f"train.steps={steps}", f"train.device={device}", "train.progress=false",
                 "train.checkpoint_every=0", "eval.every=0", "eval.save_images=false", "eval.lpips=false",
                 f"output.dir={workdir}", f"model.sh_degree={knobs['sh_degree']}",
                 f"model.sh_interval={max(1, steps // 8)}"]
    overrides += [f"train.{k}={v}" for k, v in knobs.items() if k != "sh_degree"]
    overrides += [f"strategy.refine_stop={int(steps * 0.8)}"]
    cfg = load_config(ROOT / "configs" / "default.yaml", overrides)
    trainer = Trainer(cfg, quiet=True)
    start = time.perf_counter()
    result = trainer.fit()
    return dict(psnr=result.metrics["psnr"], train_s=time.perf_counter() - start,
                primitives=trainer.model.num_primitives)


def interleaved_timings(scene, W, H, settings, device, repeats, rounds):
    """{setting key: (fwd_ms, fwd_bwd_ms, fwd_spread)}, timing every setting once per round."""
    per_round = {key: [] for key in settings}
    for r in range(rounds):
        for key, knobs in settings.items():
            per_round[key].append(timings(scene, W, H, knobs, device, repeats))
        print(f"timing round {r + 1}/{rounds} done", flush=True)
    out = {}
    for key, values in per_round.items():
        fwd = sorted(v[0] for v in values)
        fb = sorted(v[1] for v in values)
        median_fwd = fwd[len(fwd) // 2]
        out[key] = (median_fwd, fb[len(fb) // 2], (fwd[-1] - fwd[0]) / median_fwd)
    return out


def pareto(rows, x, y, better_y_is_lower):
    """Rows not beaten on both x (time, lower is better) and y by another row."""
    def beats(o, r):
        oy, ry = (o[y], r[y]) if better_y_is_lower else (-o[y], -r[y])
        return o[x] <= r[x] and oy <= ry and (o[x], oy) != (r[x], ry)

    rows = [r for r in rows if r.get(y) is not None]
    return sorted((r for r in rows if not any(beats(o, r) for o in rows)), key=lambda r: r[x])


def plot(rows, fronts, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("max_err", "max |RGB error| vs float64 reference", True)]
    if any(r.get("psnr") is not None for r in rows):
        panels.append(("psnr", "held-out PSNR after the training budget (dB)", False))
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4.2), squeeze=False)
    for ax, (y, label, log) in zip(axes[0], panels):
        for knob in SWEEPS:
            pts = [r for r in rows if r["knob"] == knob and r.get(y) is not None]
            ys = [max(p[y], 1e-8) if log else p[y] for p in pts]
            ax.scatter([p["fwd_ms"] for p in pts], ys, label=knob, s=18)
            for p, v in zip(pts, ys):
                ax.annotate(f"{p['value']:.3g}", (p["fwd_ms"], v), fontsize=7)
        front = fronts[y]
        ax.plot([r["fwd_ms"] for r in front], [max(r[y], 1e-8) if log else r[y] for r in front], "k--", lw=0.8,
                label="Pareto front")
        ax.set_xlabel("forward render time (ms)")
        ax.set_ylabel(label)
        if log:
            ax.set_yscale("log")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n", type=int, default=20_000)
    ap.add_argument("--resolution", default="320x240")
    ap.add_argument("--pixels", type=int, default=96)
    ap.add_argument("--train-steps", type=int, default=300, help="training budget per setting (0: no training)")
    ap.add_argument("--only", default="", help="comma-separated knobs to sweep (default: all)")
    ap.add_argument("--rounds", type=int, default=None, help="interleaved timing rounds (default: 5 GPU, 3 CPU)")
    args = ap.parse_args()
    W, H = (int(v) for v in args.resolution.split("x"))
    scene, W, H = degree3_scene(args.n, W, H, args.device)
    g = torch.Generator().manual_seed(0)
    pixels = torch.stack([torch.randint(0, W, (args.pixels,), generator=g),
                          torch.randint(0, H, (args.pixels,), generator=g)], -1).to(args.device)
    ref = reference_rgb(scene, W, H, pixels)
    gpu = args.device.startswith("cuda")
    repeats = 20 if gpu else 3
    rounds = args.rounds or (5 if gpu else 3)
    knobs_swept = [k for k in SWEEPS if not args.only or k in args.only.split(",")]
    sweep = [(knob, value, dict(DEFAULTS, **{knob: value})) for knob in knobs_swept for value in SWEEPS[knob]]
    settings = {tuple(sorted(knobs.items())): knobs for _, _, knobs in sweep}  # the defaults recur in every sweep
    timed = interleaved_timings(scene, W, H, settings, args.device, repeats, rounds)
    trained = {}  # effective settings -> training result
    rows = []
    with tempfile.TemporaryDirectory(prefix="warpgs-speed-vs-error-") as tmp:
        for knob, value, knobs in sweep:
            key = tuple(sorted(knobs.items()))
            fwd_ms, fb_ms, spread = timed[key]
            row = dict(knob=knob, value=value, fwd_ms=fwd_ms, fwd_bwd_ms=fb_ms, fwd_spread=spread,
                       max_err=rgb_error(scene, W, H, knobs, pixels, ref))
            if args.train_steps > 0:
                if key not in trained:
                    trained[key] = train_psnr(knobs, args.train_steps, args.device, Path(tmp) / f"run{len(trained)}")
                row.update(trained[key])
            rows.append(row)
            print(f"{knob}={value:.4g}: fwd {fwd_ms:.2f} ms, fwd+bwd {fb_ms:.2f} ms, max err {row['max_err']:.2e}"
                  + (f", PSNR {row['psnr']:.2f} dB ({row['train_s']:.0f} s)" if "psnr" in row else ""), flush=True)
    fronts = {"max_err": pareto(rows, "fwd_ms", "max_err", True), "psnr": pareto(rows, "fwd_ms", "psnr", False)}
    print(f"\n{args.n} Gaussians (SH degree 3) at {W}x{H} on {args.device}; training budget {args.train_steps} steps")
    print_table(rows, ["knob", "value", "fwd_ms", "fwd_bwd_ms", "fwd_spread", "max_err", "psnr", "train_s",
                       "primitives"])
    for y, front in fronts.items():
        if front:
            print(f"Pareto front (forward time vs {y}): " + ", ".join(f"{r['knob']}={r['value']:.4g}" for r in front))
    path = write_json(f"speed_vs_error_{args.device.split(':')[0]}", dict(
        n=args.n, width=W, height=H, device=args.device, train_steps=args.train_steps, timing_rounds=rounds,
        repeats_per_round=repeats,
        train_config="configs/default.yaml", defaults=DEFAULTS, rows=rows, pareto=fronts))
    try:
        png = path.with_suffix(".png")
        plot(rows, fronts, png)
        print(f"wrote {path} and {png}")
    except ImportError:
        print(f"wrote {path} (install matplotlib for the plot: pip install -e '.[bench]')")


if __name__ == "__main__":
    main()
