"""Pool real_capture.py results over seeds: per capture and mark, warpgs's held-out PSNR against gsplat's loop,
paired by seed (the two systems of one seed may come from one file or from two `--only` files).

    python benchmarks/real_capture_seeds.py OUT_NAME benchmarks/results/real_capture_beer_*_beerB*.json

With --against-best (issue 31's target for the default `train.steps=auto` run): warpgs's final PSNR against the
best point of gsplat's curve, and warpgs's training seconds over gsplat's whole run's, per capture and seed; a time
ratio counts as a pair only when both runs came from one file or from the same host and GPU (real_capture.py records
where it ran and the host's load when it ended), and the summary says how many are not.

Prints one row per capture, seed and mark and a summary per capture and mark (seeds, mean, sd and standard error
of the paired difference, the worst seed); writes benchmarks/results/OUT_NAME.json. A capture's seed may appear once
per system: pass the files of one code version, not old and new together; `FILE:gsplat` (or `:warpgs`) takes one
system from a file that holds both. Two runs pair only on the same scene (real_capture.py's description: views,
split, resolution, SfM points); a pair on different copies of a capture is listed, marked, and left out of the
summary."""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path
from typing import Optional

from common import print_table, read_results, write_json

SYSTEMS = ("warpgs", "gsplat")  # real_capture.py's names for the Trainer and the plain gsplat loop


def parse_file_arg(arg: str) -> tuple[str, Optional[str]]:
    """`FILE` or `FILE:system` -> (file, the one system to take or None for all)."""
    head, sep, tail = arg.rpartition(":")
    if sep and tail in SYSTEMS:
        return head, tail
    return arg, None


def scene_key(payload: dict) -> Optional[str]:
    """real_capture.py's scene description without the folder it was read from ("colmap at /tmp/data/beer: 71
    views ..." -> "colmap: 71 views ..."): two machines' copies of one capture compare, two versions do not."""
    scene = payload.get("scene")
    if not scene:
        return None
    head, sep, rest = scene.partition(":")
    return head.split(" at ")[0] + sep + rest


def collect(payloads: list[tuple[str, dict]], only: dict) -> dict:
    """{(capture, seed): {system: (file, payload, run)}} for the two compared systems; a capture, seed and system
    given twice stops the run, naming both files."""
    table: dict = {}
    for name, p in payloads:
        for key in ("data", "seed", "runs"):
            if key not in p:
                raise SystemExit(f"{name}: no {key!r}: not a real_capture.py result")
        capture = Path(p["data"]).name
        for run in p["runs"]:
            if run["system"] not in SYSTEMS or only.get(name) not in (None, run["system"]):
                continue  # e.g. the gsplat loop with warpgs's rasterizer (--loop-raster), or a system not asked for
            slot = table.setdefault((capture, p["seed"]), {})
            if run["system"] in slot:
                raise SystemExit(f"{name}: {capture} seed {p['seed']} {run['system']} is also in "
                                 f"{slot[run['system']][0]}: pass one result per capture, seed and system "
                                 f"(FILE:gsplat takes one system of a file)")
            slot[run["system"]] = (name, p, run)
    return table


def same_scene(slot: dict) -> Optional[bool]:
    """Whether both systems ran on the same copy of the capture (None when a file does not describe its scene)."""
    keys = [scene_key(slot[s][1]) for s in SYSTEMS]
    return None if None in keys else keys[0] == keys[1]


def paired(table: dict, marks: list[int]) -> list[dict]:
    """One row per capture, seed and mark where both systems were scored at that mark."""
    rows = []
    for (capture, seed), slot in sorted(table.items()):
        if len(slot) < 2:
            continue
        w, g = ({pt["step"]: pt["psnr"] for pt in slot[s][2]["points"]} for s in SYSTEMS)
        for mark in marks:
            if mark in w and mark in g:
                rows.append({"capture": capture, "seed": seed, "step": mark, "warpgs": w[mark], "gsplat": g[mark],
                             "delta": w[mark] - g[mark], "same_scene": same_scene(slot)})
    return rows


def delta_stats(d: list[float]) -> dict:
    """Mean, sd and the mean's standard error of per-seed differences (sd and se None for one seed)."""
    sd = statistics.stdev(d) if len(d) > 1 else None
    # the mean's standard error: a target closer to the mean than about two of these is not resolved
    se = sd / len(d) ** 0.5 if sd is not None else None
    return {"delta_mean": statistics.fmean(d), "delta_sd": sd, "delta_se": se}


def summary(rows: list[dict]) -> list[dict]:
    out = []
    for capture, step in sorted({(r["capture"], r["step"]) for r in rows}):
        d = [r["delta"] for r in rows if r["capture"] == capture and r["step"] == step]
        mean_w = statistics.fmean(r["warpgs"] for r in rows if r["capture"] == capture and r["step"] == step)
        mean_g = statistics.fmean(r["gsplat"] for r in rows if r["capture"] == capture and r["step"] == step)
        out.append({"capture": capture, "step": step, "seeds": len(d), "warpgs_mean": mean_w, "gsplat_mean": mean_g,
                    **delta_stats(d), "delta_min": min(d)})
    return out


def against_best(table: dict) -> list[dict]:
    """Issue 31's target for warpgs's default run (train.steps=auto): per capture and seed, warpgs's final held-out
    PSNR against the best point of gsplat's curve, and warpgs's training seconds over gsplat's whole run's."""
    rows = []
    for (capture, seed), slot in sorted(table.items()):
        if len(slot) < 2:
            continue
        (w_file, w_payload, w), (g_file, g_payload, g) = slot["warpgs"], slot["gsplat"]
        w_host, g_host = w_payload.get("host"), g_payload.get("host")
        best = max(g["points"], key=lambda pt: pt["psnr"])
        loads = [h["load_per_core"] for h in (w_host, g_host) if h and h.get("load_per_core") is not None]
        rows.append({"capture": capture, "seed": seed, "warpgs_steps": w["final"].get("steps"),
                     "warpgs": w["final"]["psnr"], "gsplat_best": best["psnr"], "gsplat_best_step": best["step"],
                     "delta": w["final"]["psnr"] - best["psnr"],
                     "time_ratio": w["final"]["train_seconds"] / g["final"]["train_seconds"],
                     "time_pair": time_pair(w_file, w_host, g_file, g_host), "max_load": max(loads, default=None),
                     "same_scene": same_scene(slot)})
    return rows


def time_pair(w_file: str, w_host: Optional[dict], g_file: str, g_host: Optional[dict]) -> Optional[bool]:
    """Whether the two runs' times compare: one file (one process), or the same host and GPU; None when a file does
    not say where it ran (results written before real_capture.py recorded its host)."""
    if w_file == g_file:
        return True
    if not w_host or not g_host:
        return None
    return all(w_host.get(k) == g_host.get(k) for k in ("hostname", "gpu_uuid"))


def best_summary(rows: list[dict]) -> list[dict]:
    out = []
    for capture in sorted({r["capture"] for r in rows}):
        mine = [r for r in rows if r["capture"] == capture]
        d = [r["delta"] for r in mine]
        out.append({"capture": capture, "seeds": len(d), **delta_stats(d),
                    "time_ratio_mean": statistics.fmean(r["time_ratio"] for r in mine)})
    return out


def kept_pairs(rows: list[dict]) -> list[dict]:
    """The rows the summary pools: pairs on different copies of a capture are left out, and said so."""
    kept = [r for r in rows if r["same_scene"] is not False]
    if len(kept) < len(rows):
        print(f"note: {len(rows) - len(kept)} of {len(rows)} rows pair runs on different copies of a capture "
              "(same_scene False: views, resolution or SfM points differ); the summary leaves them out")
    if not kept:
        raise SystemExit("no pair ran on the same copy of its capture")
    return kept


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("name", help="output name (benchmarks/results/NAME.json)")
    ap.add_argument("files", nargs="+", help="real_capture.py result JSON files; FILE:gsplat or FILE:warpgs takes "
                                                 "one system of a file")
    ap.add_argument("--marks", default="7000,30000", help="comma-separated steps to compare")
    ap.add_argument("--against-best", action="store_true",
                    help="warpgs's final PSNR (e.g. train.steps=auto) against the best point of gsplat's curve, and "
                         "the training-time ratio to gsplat's whole run (issue 31's target)")
    args = ap.parse_args(argv)
    chosen = [parse_file_arg(f) for f in args.files]
    payloads = read_results([f for f, _ in chosen], "real_capture.py result")
    table = collect(payloads, dict(chosen))
    if args.against_best:
        rows = against_best(table)
        if not rows:
            raise SystemExit("no capture and seed has both systems")
        print_table(rows, ["capture", "seed", "warpgs_steps", "warpgs", "gsplat_best", "gsplat_best_step", "delta",
                           "time_ratio", "time_pair", "same_scene", "max_load"])
        stats = best_summary(kept_pairs(rows))
        print()
        print_table(stats, ["capture", "seeds", "delta_mean", "delta_sd", "delta_se", "time_ratio_mean"])
        overall = {"delta_mean_over_captures": statistics.fmean(r["delta_mean"] for r in stats),
                   "worst_capture_delta": min(r["delta_mean"] for r in stats),
                   "time_ratio_mean_over_captures": statistics.fmean(r["time_ratio_mean"] for r in stats)}
        overall["time_ratios_not_pairs"] = sum(r["time_pair"] is not True for r in rows)
        print(f"\nover captures: delta {overall['delta_mean_over_captures']:+.2f} dB (worst capture "
              f"{overall['worst_capture_delta']:+.2f}), time ratio {overall['time_ratio_mean_over_captures']:.2f} "
              f"(target: delta >= 0, no capture below -0.3, ratio <= 0.5)")
        if overall["time_ratios_not_pairs"]:
            print(f"note: {overall['time_ratios_not_pairs']} of {len(rows)} time ratios are not pairs (the two runs "
                  "came from different hosts or GPUs, or a file does not say where it ran): the time ratio is not a "
                  "measurement")
        payload = {"files": args.files, "mode": "against_best", "rows": rows, "summary": stats,
                   "overall": overall}
        print(f"\nwrote {write_json(args.name, payload)}")
        return payload
    marks = [int(m) for m in args.marks.split(",")]
    rows = paired(table, marks)
    if not rows:
        raise SystemExit("no capture has both systems scored at " + args.marks)
    print_table(rows, ["capture", "seed", "step", "warpgs", "gsplat", "delta", "same_scene"])
    print()
    stats = summary(kept_pairs(rows))
    print_table(stats, ["capture", "step", "seeds", "warpgs_mean", "gsplat_mean", "delta_mean", "delta_sd",
                        "delta_se", "delta_min"])
    payload = {"files": args.files, "marks": marks, "rows": rows, "summary": stats}
    print(f"\nwrote {write_json(args.name, payload)}")
    return payload


if __name__ == "__main__":
    sys.exit(main() and 0)
