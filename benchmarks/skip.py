"""What skipping saves: each line times the renderer with and without work a scene does not need.

    python benchmarks/skip.py                    # CPU: 50k Gaussians at 800x600
    python benchmarks/skip.py --device cuda --n 1000000 --resolution 1920x1080

Measured side by side in one run (same scene, same process); writes benchmarks/results/skip_<device>.json.
"""
from __future__ import annotations

import argparse

import torch

from common import print_table, standard_scenes_module, time_call, write_json
from warpgs import rasterize


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n", type=int, default=50_000)
    ap.add_argument("--resolution", default="800x600")
    ap.add_argument("--features", type=int, default=16)
    args = ap.parse_args()
    W, H = (int(v) for v in args.resolution.split("x"))
    dev = args.device
    means, quats, scales, opacities, colors, viewmat, K, W, H = standard_scenes_module().random_scene(
        args.n, width=W, height=H, device=dev)
    g = torch.Generator().manual_seed(1)
    features = torch.rand(args.n, args.features, generator=g).to(dev)
    sh = torch.zeros(args.n, 16, 3, device=dev)
    sh[:, 0] = (colors - 0.5) / 0.28209479177387814
    sh[:, 1:] = torch.randn(args.n, 15, 3, generator=g).to(dev) * 0.05
    reps = 20 if dev.startswith("cuda") else 3

    def fwd(outputs=("rgb",), **kw):
        args_ = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors)
        args_.update({k: v for k, v in kw.items() if k in args_})
        extra = {k: v for k, v in kw.items() if k not in args_}
        return lambda: rasterize(args_["means"], args_["quats"], args_["scales"], args_["opacities"], args_["colors"],
                                 viewmat, K, W, H, outputs=outputs, features=features, check_inputs=False, **extra)

    def fwd_bwd(trainable):
        def run():
            leaves = {k: v.detach().requires_grad_(k in trainable) for k, v in
                      dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors).items()}
            out = rasterize(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"],
                            viewmat, K, W, H, outputs=("rgb",), check_inputs=False)
            out.rgb.sum().backward()
        return run

    t = lambda fn: time_call(fn, dev, warmup=2, repeats=reps)  # noqa: E731
    rows = []

    def compare(what, needed, full, label_needed, label_full):
        a, b = t(needed), t(full)
        rows.append(dict(skip=what, with_skip=label_needed, ms=a, without=label_full, ms_without=b, saved=1 - a / b))

    compare("outputs not asked for", fwd(("rgb",)), fwd(("rgb", "alpha", "depth", "inv_depth", "features")),
            "rgb only", f"rgb+alpha+depth+inv_depth+{args.features} features")
    compare("depth pass", fwd(("rgb",)), fwd(("rgb", "depth")), "rgb", "rgb+depth")
    compare("feature (language) pass", fwd(("rgb",)), fwd(("rgb", "features")), "rgb", f"rgb+{args.features} features")
    compare("SH bands above the active degree", fwd(colors=sh, sh_degree=0), fwd(colors=sh, sh_degree=3),
            "degree 0 of 16 coefficients", "degree 3")
    compare("frozen parameters' gradients", fwd_bwd({"opacities"}),
            fwd_bwd({"means", "quats", "scales", "opacities", "colors"}), "opacities learnt", "all learnt")

    # Culling: as many extra Gaussians again, half behind the camera and half too faint to reach 1/255.
    extra = means.clone()
    extra[: args.n // 2, 2] = -extra[: args.n // 2, 2]
    faint = opacities.clone()
    faint[args.n // 2:] = 0.003
    more = dict(means=torch.cat([means, extra]), quats=torch.cat([quats, quats]), scales=torch.cat([scales, scales]),
                opacities=torch.cat([opacities, torch.where(torch.arange(args.n, device=dev) < args.n // 2, opacities, faint)]),
                colors=torch.cat([colors, colors]))
    feats2 = torch.cat([features, features])
    base, padded = t(fwd(("rgb",))), t(lambda: rasterize(more["means"], more["quats"], more["scales"], more["opacities"],
                                                        more["colors"], viewmat, K, W, H, features=feats2,
                                                        check_inputs=False))
    rows.append(dict(skip="culled Gaussians (behind camera / alpha < 1/255)", with_skip=f"{args.n} visible", ms=base,
                     without=f"+{args.n} culled", ms_without=padded, saved=None,
                     note=f"{args.n} culled Gaussians add {(padded - base) / base:.1%} to the time of {args.n} visible ones"))

    # Empty tiles: the same scene moved out of view leaves only empty tiles.
    away = means + torch.tensor([0.0, 0.0, -100.0], device=dev)
    empty = t(fwd(("rgb",), means=away))
    rows.append(dict(skip="empty tiles", with_skip="all tiles empty", ms=empty, without="scene in view", ms_without=base,
                     saved=1 - empty / base))

    print(f"{args.n} Gaussians at {W}x{H} on {dev}")
    print_table(rows, ["skip", "with_skip", "ms", "without", "ms_without", "saved"])
    for r in rows:
        if r.get("note"):
            print(f"- {r['skip']}: {r['note']}")
    path = write_json(f"skip_{dev.split(':')[0]}", dict(n=args.n, width=W, height=H, device=dev, rows=rows))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
