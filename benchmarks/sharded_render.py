"""Model-parallel rendering (warpgs.render.sharded) against one process rendering the whole model, per view,
forward + backward; run under torchrun, one process per GPU (or CPU process with gloo):

    torchrun --standalone --nproc_per_node=2 benchmarks/sharded_render.py --device cuda --primitives 1000000 --size 1920x1080
    torchrun --standalone --nproc_per_node=2 benchmarks/sharded_render.py --device cpu --primitives 20000 --size 320x180

Every rank builds the same standard scene (../shared/bench/scenes.py) and keeps its shard of it; rank r's camera
is the scene's, moved sideways by r x --baseline. Interleaved rounds on every rank, medians in ms:
- whole: `rasterize` of all N primitives for this rank's camera (one GPU holding the whole model);
- sharded: `render_sharded` of the shards for every rank's camera (each rank holding N/R), with the exchange.
Also the splats sent per step (rows of 13 floats; blocks travel at their own sizes). Model parallelism buys
memory (N/R primitives, their Adam state and gradients a rank), not speed: `sharded / whole` is its cost per view.
Writes benchmarks/results/sharded_render_<device>[_<tag>].json ($OUT when set) from rank 0."""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.distributed as dist

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, standard_scenes_module, sync, write_json  # noqa: E402

sys.path.insert(0, str(ROOT))
from warpgs import rasterize  # noqa: E402
from warpgs.render.sharded import reaches_image, render_sharded  # noqa: E402
from warpgs.render.splats import SPLAT_COLUMNS, project_splats  # noqa: E402
from warpgs.train.distributed import Ranks, shutdown_process_group  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", help="cpu (gloo) or cuda (NCCL, one GPU a rank)")
    ap.add_argument("--primitives", type=int, default=20_000, help="primitives in the whole model")
    ap.add_argument("--size", default="320x180", help="image WxH")
    ap.add_argument("--baseline", type=float, default=0.3, help="sideways step between the ranks' cameras")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    cuda = args.device.startswith("cuda")
    if cuda:
        os.environ.setdefault("NCCL_NVLS_ENABLE", "0")  # NVLink multicast off on shared hosts (docs/distributed.md)
    dist.init_process_group("nccl" if cuda else "gloo")
    rank, world = dist.get_rank(), dist.get_world_size()
    device = f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}" if cuda else "cpu"
    if cuda:
        torch.cuda.set_device(device)
    ranks = Ranks(rank, world, backend="nccl" if cuda else "gloo")
    width, height = (int(v) for v in args.size.lower().split("x"))
    means, quats, scales, opacities, colors, viewmat, K, W, H = standard_scenes_module().random_scene(
        args.primitives, width, height, device=device)
    viewmats = viewmat.repeat(world, 1, 1)
    viewmats[:, 0, 3] = -args.baseline * (torch.arange(world, device=device) - (world - 1) / 2)
    Ks = K.repeat(world, 1, 1)
    mine = ranks.shard(args.primitives)
    shard = [t[mine].clone().requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
    whole = [t.clone().requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
    weight = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(rank)).to(device)

    def run_whole():
        out = rasterize(*whole, viewmats[rank], Ks[rank], W, H, outputs=("rgb",))
        (out.rgb * weight).sum().backward()

    def run_sharded():
        out = render_sharded(*shard, viewmats, Ks, W, H, outputs=("rgb",))
        (out.rgb * weight).sum().backward()

    with torch.no_grad():
        rows = []
        for j in range(world):
            s = project_splats(*shard, viewmats[j], Ks[j], W, H)
            rows.append(int(reaches_image(s, W, H).sum()))
    times = {"whole": [], "sharded": []}
    for fn in (run_whole, run_sharded):  # warm-up: kernel loading
        fn()
    for _ in range(args.rounds):
        for name, fn in (("whole", run_whole), ("sharded", run_sharded)):
            sync(device)
            t0 = time.perf_counter()
            fn()
            sync(device)
            times[name].append((time.perf_counter() - t0) * 1e3)
    mine_result = {"rank": rank, "primitives": mine.stop - mine.start, "rows_sent_to": rows,
                   "whole_ms": statistics.median(times["whole"]), "sharded_ms": statistics.median(times["sharded"])}
    everyone = ranks.all_gather_object(mine_result, what="gathering the timings")
    shutdown_process_group()
    if rank != 0:
        return {}
    payload = {"device": args.device, "gpu": torch.cuda.get_device_name(0) if cuda else None, "ranks": world,
               "n": args.primitives, "size": [W, H], "rounds": args.rounds, "per_rank": everyone,
               "splat_bytes": SPLAT_COLUMNS * 4,
               "bytes_sent_per_step": sum(sum(r["rows_sent_to"]) for r in everyone) * SPLAT_COLUMNS * 4,
               "sharded_over_whole": [r["sharded_ms"] / r["whole_ms"] for r in everyone],
               "command": " ".join(sys.argv)}
    if not cuda:
        payload["note"] = "CPU processes share the machine's cores: the times say nothing about GPU cost"
    for r in everyone:
        print(f"rank {r['rank']}: {r['primitives']} primitives, whole {r['whole_ms']:.1f} ms, sharded "
              f"{r['sharded_ms']:.1f} ms ({r['sharded_ms'] / r['whole_ms']:.2f}x), rows sent {r['rows_sent_to']}")
    name = "sharded_render_" + args.device.split(":")[0] + (f"_{args.tag}" if args.tag else "")
    print(f"wrote {write_json(name, payload)}")
    return payload


if __name__ == "__main__":
    main()
