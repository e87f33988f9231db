"""The Marr depth terms (warpgs/losses/marr.py: depth, depth_grad, depth_local) of a training step, eager against
replayed from CUDA graphs (WARPGS_LOSS_GRAPHS=0 / on), in one process: values and gradients compared, then the
time of each term's forward + backward and of the three together.

    python benchmarks/marr_graphs.py --sizes 960x540,480x270 --calls 200 --rounds 3

The inputs are a training step's: the render's inv_depth and alpha (requiring gradients; some alpha below
alpha_min), the batch's prior (with NaN and non-positive pixels) and valid mask, the confidence on the batch's view
(with zeros). Checked on each size, every time with new tensors: the trainer's signature, without a confidence, with
a batch mask, under other settings (marr.configure), and a value kept across the next replay (compute_losses keeps
them). Exits 1 when a difference is beyond float32 tolerance or when no graph was captured on a GPU. On the CPU
nothing is graphed (both arms run the terms as written): a smoke run.

Writes benchmarks/results/marr_graphs_<cuda|cpu>[_<tag>].json ($OUT/... when OUT is set): per size, each check's
largest differences, each arm's milliseconds per call in every round (and the host's share), the ratios.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from types import SimpleNamespace

import torch

from common import run_host, sync, write_json
from warpgs.losses import compute_losses, get_loss, marr, resolve_losses

TERMS = ("depth", "depth_grad", "depth_local")
VALUE_TOL = (1e-6, 1e-5)  # (absolute, relative): float32 reductions in another order at most
GRAD_TOL = 1e-4  # of the largest gradient
OTHER_SETTINGS = {"alpha_eps": 1e-3, "alpha_min": 0.3, "confidence_power": 2.0}


def step_inputs(width: int, height: int, device, g: torch.Generator, confidence: bool = True, mask: bool = False):
    """(render, batch) as a training step has them, new tensors each call."""
    def rand(*shape):
        return torch.rand(*shape, device=device, generator=g)

    alpha = rand(height, width, 1) * 1.1
    alpha[: height // 8] *= 0.1  # a band below alpha_min
    inv = (alpha * (0.2 + rand(height, width, 1))).requires_grad_(True)
    alpha.requires_grad_(True)
    prior = 0.2 + rand(height, width, 1)
    prior[rand(height, width, 1) < 0.02] = float("nan")
    prior[rand(height, width, 1) < 0.02] = -1.0
    view = SimpleNamespace(inv_depth_confidence=None)
    if confidence:
        view.inv_depth_confidence = rand(height, width, 1) * (rand(height, width, 1) > 0.05)
    batch = {"inv_depth_prior": prior, "inv_depth_valid": rand(height, width, 1) > 0.1, "view": view}
    if mask:
        batch["mask"] = rand(height, width, 1) > 0.1
    return SimpleNamespace(inv_depth=inv, alpha=alpha), batch


def graphs_on(on: bool) -> None:
    os.environ["WARPGS_LOSS_GRAPHS"] = "1" if on else "0"


def value_and_grads(names, out, batch) -> tuple:
    out.inv_depth.grad = out.alpha.grad = None
    loss = sum(get_loss(n).fn(out, batch, None, 0) for n in names)
    loss.backward()
    return loss.detach().clone(), out.inv_depth.grad.clone(), out.alpha.grad.clone()


def differences(got: tuple, want: tuple) -> dict:
    value = (got[0] - want[0]).abs().item()
    grad_scale = max(want[1].abs().max().item(), want[2].abs().max().item(), 1e-30)
    grad = max((got[1] - want[1]).abs().max().item(), (got[2] - want[2]).abs().max().item())
    ok = value <= VALUE_TOL[0] + VALUE_TOL[1] * abs(want[0].item()) and grad <= GRAD_TOL * grad_scale
    return {"value": want[0].item(), "value_abs_diff": value, "value_rel_diff": value / max(abs(want[0].item()), 1e-30),
            "grad_abs_diff": grad, "grad_rel_diff": grad / grad_scale, "ok": bool(ok)}


def check(width: int, height: int, device, g: torch.Generator) -> dict:
    """{case: {term: differences}}, graphed against eager on the same new tensors."""
    cases = {"trainer": {}, "no_confidence": {"confidence": False}, "batch_mask": {"mask": True},
             "settings": {}, "trainer_again": {}}
    found = {}
    saved = {k: getattr(marr.SETTINGS, k) for k in OTHER_SETTINGS}
    try:
        for case, kwargs in cases.items():
            marr.configure(**(OTHER_SETTINGS if case == "settings" else saved))
            out, batch = step_inputs(width, height, device, g, **kwargs)
            rows = {}
            for name in TERMS:
                graphs_on(False)
                want = value_and_grads((name,), out, batch)
                graphs_on(True)
                rows[name] = differences(value_and_grads((name,), out, batch), want)
            found[case] = rows
        # compute_losses keeps each value: the next view's replay must not change it
        terms = resolve_losses({n: 1.0 for n in TERMS})
        first_inputs = step_inputs(width, height, device, g)
        first = compute_losses(terms, *first_inputs, None, 0, 100)
        compute_losses(terms, *step_inputs(width, height, device, g), None, 0, 100)
        graphs_on(False)
        eager = compute_losses(terms, *first_inputs, None, 0, 100)
        graphs_on(True)
        kept = {n: (first.values[n] - eager.values[n]).abs().item() for n in TERMS}
        found["kept_values"] = {n: {"value_abs_diff": d, "ok": d <= VALUE_TOL[0] + VALUE_TOL[1] * abs(
            eager.values[n].item())} for n, d in kept.items()}
    finally:
        marr.configure(**saved)
    return found


def time_calls(names, inputs, calls: int, device) -> tuple:
    """(ms per call, ms of it the host spent issuing: before the final synchronisation); the inputs rotate, as a
    step's views do."""
    sync(device)
    t0 = time.perf_counter()
    for i in range(calls):
        out, batch = inputs[i % len(inputs)]
        out.inv_depth.grad = out.alpha.grad = None
        sum(get_loss(n).fn(out, batch, None, 0) for n in names).backward()
    issued = time.perf_counter()
    sync(device)
    return 1e3 * (time.perf_counter() - t0) / calls, 1e3 * (issued - t0) / calls


def captured_graphs() -> int:
    return sum(len(s.graphs) for k in marr._GRAPHS.values() for s in k.keys.values())


def measure(width: int, height: int, calls: int, rounds: int, device) -> dict:
    g = torch.Generator(device=device).manual_seed(0)
    row = {"width": width, "height": height}
    for graphs in marr._GRAPHS.values():  # this size's graphs only (a term keeps 4 signatures a key)
        graphs.keys.clear()
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()
        torch.cuda.empty_cache()
        reserved = torch.cuda.memory_reserved()
    row["checks"] = check(width, height, device, g)
    row["captured_graphs"] = captured_graphs()
    if torch.device(device).type == "cuda":
        row["reserved_mb_after_checks"] = (torch.cuda.memory_reserved() - reserved) / 2 ** 20
    inputs = [step_inputs(width, height, device, g) for _ in range(4)]
    timed = {**{n: (n,) for n in TERMS}, "all": TERMS}
    row["timings"] = {what: {arm: {"ms": [], "host_ms": []} for arm in ("eager", "graphed")} for what in timed}
    for _ in range(rounds):
        for what, names in timed.items():
            for arm in ("eager", "graphed"):
                graphs_on(arm == "graphed")
                time_calls(names, inputs, 3, device)  # warm
                ms, host_ms = time_calls(names, inputs, calls, device)
                row["timings"][what][arm]["ms"].append(ms)
                row["timings"][what][arm]["host_ms"].append(host_ms)
    graphs_on(True)
    for what, arms in row["timings"].items():
        eager, graphed = (statistics.median(arms[a]["ms"]) for a in ("eager", "graphed"))
        arms["eager_over_graphed"] = eager / graphed
    return row


def report(row: dict) -> bool:
    ok = True
    size = f"{row['width']}x{row['height']}"
    for case, terms in row["checks"].items():
        for name, d in terms.items():
            ok &= d["ok"]
            grad = (f", gradient abs {d['grad_abs_diff']:.2e} rel {d['grad_rel_diff']:.2e}" if "grad_abs_diff" in d
                    else "")
            rel = f" rel {d['value_rel_diff']:.2e}" if "value_rel_diff" in d else ""
            print(f"{size} {case:14s} {name:12s} value abs {d['value_abs_diff']:.2e}{rel}{grad}"
                  f"{'' if d['ok'] else '  BEYOND TOLERANCE'}", flush=True)
    for what, arms in row["timings"].items():
        e, gr = (statistics.median(arms[a]["ms"]) for a in ("eager", "graphed"))
        he, hg = (statistics.median(arms[a]["host_ms"]) for a in ("eager", "graphed"))
        print(f"{size} {what:12s} eager {e:7.3f} ms (host {he:.3f})  graphed {gr:7.3f} ms (host {hg:.3f})  "
              f"eager/graphed {arms['eager_over_graphed']:.2f}", flush=True)
    print(f"{size} graphs captured: {row['captured_graphs']}"
          + (f", {row['reserved_mb_after_checks']:.0f} MiB more reserved" if "reserved_mb_after_checks" in row
             else ""), flush=True)
    return bool(ok)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="960x540,480x270", help="WxH,WxH")
    ap.add_argument("--calls", type=int, default=200, help="timed calls per arm and round")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    if not cuda:
        print("marr_graphs.py: no CUDA device, nothing is graphed (a smoke run: both arms run the terms as written)",
              flush=True)
    before = os.environ.get("WARPGS_LOSS_GRAPHS")
    rows, ok = [], True
    try:
        for size in args.sizes.split(","):
            width, height = (int(v) for v in size.lower().split("x"))
            row = measure(width, height, args.calls, args.rounds, device)
            rows.append(row)
            ok &= report(row)
            if cuda and row["captured_graphs"] == 0:
                print(f"{width}x{height}: no graph was captured on {device}", flush=True)
                ok = False
    finally:
        if before is None:
            os.environ.pop("WARPGS_LOSS_GRAPHS", None)
        else:
            os.environ["WARPGS_LOSS_GRAPHS"] = before
    result = {"host": run_host(str(device)), "device": str(device), "graphs": cuda, "calls": args.calls,
              "rounds": args.rounds, "tolerance": {"value": VALUE_TOL, "grad_of_largest": GRAD_TOL}, "ok": ok,
              "rows": rows}
    path = write_json(f"marr_graphs_{device.type}" + (f"_{args.tag}" if args.tag else ""), result)
    print(f"{'ok' if ok else 'FAILED'}: {path}", flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
