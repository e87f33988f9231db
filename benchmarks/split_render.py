"""The render cut at the projected splats (what model-parallel training runs a view through) against the whole op,
forward + backward of RGB + expected depth, one process on one device:

    python benchmarks/split_render.py --device cuda --sizes 100000,1000000 --resolution 1920x1080
    python benchmarks/split_render.py --device cuda --compare-module OLD_splats.py   # also another version's ops

- whole: `rasterize` of the standard scene (../shared/bench/scenes.py);
- split: `project_splats`, the valid rows selected and packed into splat rows and unpacked again (what the exchange
  between ranks sends), then `blend_splats`; no process group: the exchange itself is not in it;
- with --compare-module FILE: the same split through FILE's `project_splats` / `Splats` / `blend_splats` (e.g. an
  earlier `warpgs/render/splats.py` from git), timed in the same rounds.
Medians of interleaved rounds of 10 calls each, in ms. Writes benchmarks/results/split_render_<device>[_<tag>].json.
"""
from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import time

import torch

from common import ROOT, run_host, standard_scenes_module, sync, write_json

sys.path.insert(0, str(ROOT))

from warpgs import rasterize  # noqa: E402
from warpgs.render import splats as current_splats  # noqa: E402

OUTPUTS = ("rgb", "alpha", "depth")


def split_render(module, leaves, viewmat, K, W, H):
    s = module.project_splats(*leaves, viewmat, K, W, H)
    s = module.Splats.unpack(s.select(s.valid).pack())
    return module.blend_splats(s, W, H, outputs=OUTPUTS)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--sizes", default="100000,1000000", help="primitive counts")
    ap.add_argument("--resolution", default="1920x1080")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--compare-module", default=None, help="a splats.py of another version, timed beside")
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    W, H = (int(v) for v in args.resolution.lower().split("x"))
    systems = {"whole": None, "split": current_splats}
    if args.compare_module:
        spec = importlib.util.spec_from_file_location("compared_splats", args.compare_module)
        other = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(other)
        systems["split (compared module)"] = other
    scenes = standard_scenes_module()
    rows = []
    for n in (int(v) for v in args.sizes.split(",")):
        means, quats, scales, opacities, colors, viewmat, K, _, _ = scenes.random_scene(n, W, H, device=args.device)
        leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opacities, colors)]

        def call(module):
            out = (rasterize(*leaves, viewmat, K, W, H, outputs=OUTPUTS) if module is None
                   else split_render(module, leaves, viewmat, K, W, H))
            (out.rgb.sum() + out.depth.sum()).backward()

        for module in systems.values():  # warm-up: kernel loading, buffers
            call(module)
            call(module)
        times = {name: [] for name in systems}
        for _ in range(args.rounds):
            for name, module in systems.items():
                for t in leaves:
                    t.grad = None
                sync(args.device)
                t0 = time.perf_counter()
                for _ in range(10):
                    call(module)
                sync(args.device)
                times[name].append((time.perf_counter() - t0) / 10 * 1e3)
        row = {"n": n, **{f"{name} ms": statistics.median(v) for name, v in times.items()}}
        for name in systems:
            if name != "whole":
                row[f"{name} / whole"] = row[f"{name} ms"] / row["whole ms"]
        rows.append(row)
        print(" | ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()), flush=True)
    name = "split_render_" + args.device.split(":")[0] + (f"_{args.tag}" if args.tag else "")
    payload = {"device": args.device, "size": [W, H], "rounds": args.rounds, "compare_module": args.compare_module,
               "rows": rows, "host": run_host(args.device), "command": " ".join(sys.argv)}
    print(f"wrote {write_json(name, payload)}")
    return payload


if __name__ == "__main__":
    main()
