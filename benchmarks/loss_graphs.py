"""The training step's D-SSIM replayed from CUDA graphs (warpgs/losses/cuda_graphs.py) against the same torch ops
launched one by one: values and gradients compared, and the time of a loss forward + backward, interleaved in
one process. CUDA only.

    python benchmarks/loss_graphs.py --sizes 800x534,1920x1080 --batch 1,2 --calls 200 --rounds 3

Writes benchmarks/results/loss_graphs_cuda[_<tag>].json: per image shape, the largest differences of the loss
and of its gradient, and the milliseconds per call of each arm in every round.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from common import run_host, write_json
from warpgs.losses.cuda_graphs import ShapeGraphs
from warpgs.metrics.image import ssim


def loss_and_grad(fn, pred, target):
    pred.grad = None
    loss = 1.0 - fn(pred, target)
    loss.backward()
    return loss.detach().clone(), pred.grad.clone()


def time_calls(fn, pred, target, calls: int) -> float:
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(calls):
        pred.grad = None
        (1.0 - fn(pred, target)).backward()
    torch.cuda.synchronize()
    return 1e3 * (time.perf_counter() - t0) / calls


def measure(width: int, height: int, batch: int, calls: int, rounds: int) -> dict:
    g = torch.Generator(device="cuda").manual_seed(0)
    shape = (batch, height, width, 3) if batch > 1 else (height, width, 3)
    pred = torch.rand(shape, device="cuda", generator=g).requires_grad_(True)
    target = torch.rand(shape, device="cuda", generator=g)
    graphed = ShapeGraphs(ssim)
    plain_loss, plain_grad = loss_and_grad(ssim, pred, target)
    errors = []
    for _ in range(3):  # replays after the capture, with new inputs each time
        with torch.no_grad():
            pred.copy_(torch.rand(shape, device="cuda", generator=g))
        plain_loss, plain_grad = loss_and_grad(ssim, pred, target)
        graph_loss, graph_grad = loss_and_grad(graphed, pred, target)
        errors.append(((graph_loss - plain_loss).abs().item(), (graph_grad - plain_grad).abs().max().item()))
    row = {"width": width, "height": height, "batch": batch, "graphs": len(graphed.graphs),
           "max_loss_diff": max(e[0] for e in errors), "max_grad_diff": max(e[1] for e in errors),
           "plain_ms": [], "graphed_ms": []}
    for _ in range(rounds):
        row["plain_ms"].append(time_calls(ssim, pred, target, calls))
        row["graphed_ms"].append(time_calls(graphed, pred, target, calls))
    row["ratio"] = statistics.median(row["graphed_ms"]) / statistics.median(row["plain_ms"])
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
        raise SystemExit("loss_graphs.py: needs a CUDA device (the graphs are CUDA graphs)")
    rows = []
    for size in args.sizes.split(","):
        width, height = (int(v) for v in size.lower().split("x"))
        for batch in (int(b) for b in args.batch.split(",")):
            row = measure(width, height, batch, args.calls, args.rounds)
            rows.append(row)
            print(f"{width}x{height} x{batch}: plain {statistics.median(row['plain_ms']):.3f} ms, graphed "
                  f"{statistics.median(row['graphed_ms']):.3f} ms ({row['ratio']:.2f}x); differences: loss "
                  f"{row['max_loss_diff']:.2e}, gradient {row['max_grad_diff']:.2e}", flush=True)
    result = {"host": run_host("cuda"), "calls": args.calls, "rows": rows}
    write_json("loss_graphs_cuda" + (f"_{args.tag}" if args.tag else ""), result)
    return result


if __name__ == "__main__":
    main()
