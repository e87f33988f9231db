"""The training step's D-SSIM three ways, interleaved in one process: torch's ops launched one by one (plain),
the same replayed from CUDA graphs (warpgs/losses/cuda_graphs.py), the Warp op (render/ssim_op.py,
`train.fused_ssim`) and the Warp op replayed from CUDA graphs. Loss and gradient compared with plain; time of a loss forward + backward. CUDA only.

    python benchmarks/ssim_loss.py --sizes 800x534,1920x1080 --batch 1,2 --calls 200 --rounds 3

Writes benchmarks/results/ssim_loss_cuda[_<tag>].json: per image shape, each arm's largest differences of the
loss and of its gradient from plain, its milliseconds per call in every round and its ratio to plain.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from common import run_host, write_json
from warpgs.losses.cuda_graphs import ShapeGraphs
from warpgs.metrics.image import ssim
from warpgs.render.ssim_op import fused_ssim


def loss_and_grad(fn, pred, target):
    pred.grad = None
    loss = 1.0 - fn(pred, target)
    loss.backward()
    return loss.detach().clone(), pred.grad.clone()


def time_calls(fn, pred, target, calls: int) -> tuple:
    """(ms per call, ms per call the host spent issuing them: before the final synchronisation)."""
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(calls):
        pred.grad = None
        (1.0 - fn(pred, target)).backward()
    issued = time.perf_counter()
    torch.cuda.synchronize()
    return 1e3 * (time.perf_counter() - t0) / calls, 1e3 * (issued - t0) / calls


def measure(width: int, height: int, batch: int, calls: int, rounds: int) -> dict:
    g = torch.Generator(device="cuda").manual_seed(0)
    shape = (batch, height, width, 3) if batch > 1 else (height, width, 3)
    pred = torch.rand(shape, device="cuda", generator=g).requires_grad_(True)
    target = torch.rand(shape, device="cuda", generator=g)
    arms = {"plain": ssim, "graphed": ShapeGraphs(ssim), "warp": fused_ssim, "warp_graphed": ShapeGraphs(fused_ssim)}
    row = {"width": width, "height": height, "batch": batch, "arms": {}, "failed": {}}
    try:  # Warp's launches inside torch's graph capture (they run on torch's current stream)
        loss_and_grad(arms["warp_graphed"], pred, target)
    except Exception as e:  # noqa: BLE001 - reported, the other arms still run
        row["failed"]["warp_graphed"] = f"{type(e).__name__}: {e}"[:500]
        print(f"warp_graphed: capture failed: {row['failed']['warp_graphed']}", flush=True)
        del arms["warp_graphed"]
    for name in arms:
        row["arms"][name] = {"max_loss_diff": 0.0, "max_grad_diff": 0.0, "ms": [], "host_ms": []}
    for _ in range(3):  # after the capture, with new inputs each time
        with torch.no_grad():
            pred.copy_(torch.rand(shape, device="cuda", generator=g))
        plain_loss, plain_grad = loss_and_grad(ssim, pred, target)
        for name, fn in arms.items():
            loss, grad = loss_and_grad(fn, pred, target)
            arm = row["arms"][name]
            arm["max_loss_diff"] = max(arm["max_loss_diff"], (loss - plain_loss).abs().item())
            arm["max_grad_diff"] = max(arm["max_grad_diff"], (grad - plain_grad).abs().max().item())
    row["max_plain_grad"] = plain_grad.abs().max().item()
    for _ in range(rounds):
        for name, fn in arms.items():
            ms, host_ms = time_calls(fn, pred, target, calls)
            row["arms"][name]["ms"].append(ms)
            row["arms"][name]["host_ms"].append(host_ms)
    plain = statistics.median(row["arms"]["plain"]["ms"])
    for arm in row["arms"].values():
        arm["ratio"] = statistics.median(arm["ms"]) / plain
    return row


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="800x534,1920x1080", help="WxH,WxH")
    ap.add_argument("--batch", default="1", help="images per call, comma-separated")
    ap.add_argument("--calls", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        raise SystemExit("ssim_loss.py: needs a CUDA device (the graphs are CUDA graphs)")
    rows = []
    for size in args.sizes.split(","):
        width, height = (int(v) for v in size.lower().split("x"))
        for batch in (int(b) for b in args.batch.split(",")):
            row = measure(width, height, batch, args.calls, args.rounds)
            rows.append(row)
            for name, arm in row["arms"].items():
                print(f"{width}x{height} x{batch} {name:8s} {statistics.median(arm['ms']):7.3f} ms ({arm['ratio']:.2f}x "
                      f"plain; host {statistics.median(arm['host_ms']):.3f} ms); differences from plain: loss {arm['max_loss_diff']:.2e}, gradient "
                      f"{arm['max_grad_diff']:.2e} (largest gradient {row['max_plain_grad']:.2e})", flush=True)
    result = {"host": run_host("cuda"), "calls": args.calls, "rows": rows}
    write_json("ssim_loss_cuda" + (f"_{args.tag}" if args.tag else ""), result)
    return result


if __name__ == "__main__":
    main()
