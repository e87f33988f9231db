"""Pool real_capture.py results over seeds: per capture and mark, warpgs's held-out PSNR against gsplat's loop,
paired by seed (the two systems of one seed may come from one file or from two `--only` files).

    python benchmarks/real_capture_seeds.py OUT_NAME benchmarks/results/real_capture_beer_*_beerB*.json

Prints one row per capture, seed and mark and a summary per capture and mark (seeds, mean, sd and standard error
of the paired difference, the worst seed); writes benchmarks/results/OUT_NAME.json. A capture's seed may appear once
per system: pass the files of one code version, not old and new together."""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

from common import print_table, read_results, write_json

SYSTEMS = ("warpgs", "gsplat")  # real_capture.py's names for the Trainer and the plain gsplat loop


def runs_by_seed(payloads: list[tuple[str, dict]]) -> dict:
    """{(capture, seed): {system: (file, {step: psnr, ...})}} for the two compared systems."""
    table: dict = {}
    for name, p in payloads:
        for key in ("data", "seed", "runs"):
            if key not in p:
                raise SystemExit(f"{name}: no {key!r}: not a real_capture.py result")
        capture = Path(p["data"]).name
        for run in p["runs"]:
            if run["system"] not in SYSTEMS:
                continue  # e.g. the gsplat loop with warpgs's rasterizer (--loop-raster)
            slot = table.setdefault((capture, p["seed"]), {})
            if run["system"] in slot:
                raise SystemExit(f"{name}: {capture} seed {p['seed']} {run['system']} is also in "
                                 f"{slot[run['system']][0]}: pass one result per capture, seed and system")
            slot[run["system"]] = (name, {pt["step"]: pt["psnr"] for pt in run["points"]})
    return table


def paired(table: dict, marks: list[int]) -> list[dict]:
    """One row per capture, seed and mark where both systems were scored at that mark."""
    rows = []
    for (capture, seed), slot in sorted(table.items()):
        if len(slot) < 2:
            continue
        w, g = slot["warpgs"][1], slot["gsplat"][1]
        for mark in marks:
            if mark in w and mark in g:
                rows.append({"capture": capture, "seed": seed, "step": mark, "warpgs": w[mark], "gsplat": g[mark],
                             "delta": w[mark] - g[mark]})
    return rows


def summary(rows: list[dict]) -> list[dict]:
    out = []
    for capture, step in sorted({(r["capture"], r["step"]) for r in rows}):
        d = [r["delta"] for r in rows if r["capture"] == capture and r["step"] == step]
        mean_w = statistics.fmean(r["warpgs"] for r in rows if r["capture"] == capture and r["step"] == step)
        mean_g = statistics.fmean(r["gsplat"] for r in rows if r["capture"] == capture and r["step"] == step)
        sd = statistics.stdev(d) if len(d) > 1 else None
        # the mean's standard error: a target closer to the mean than about two of these is not resolved
        se = sd / len(d) ** 0.5 if sd is not None else None
        out.append({"capture": capture, "step": step, "seeds": len(d), "warpgs_mean": mean_w, "gsplat_mean": mean_g,
                    "delta_mean": statistics.fmean(d), "delta_sd": sd, "delta_se": se, "delta_min": min(d)})
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("name", help="output name (benchmarks/results/NAME.json)")
    ap.add_argument("files", nargs="+", help="real_capture.py result JSON files")
    ap.add_argument("--marks", default="7000,30000", help="comma-separated steps to compare")
    args = ap.parse_args(argv)
    payloads = read_results(args.files, "real_capture.py result")
    marks = [int(m) for m in args.marks.split(",")]
    rows = paired(runs_by_seed(payloads), marks)
    if not rows:
        raise SystemExit("no capture has both systems scored at " + args.marks)
    print_table(rows, ["capture", "seed", "step", "warpgs", "gsplat", "delta"])
    print()
    stats = summary(rows)
    print_table(stats, ["capture", "step", "seeds", "warpgs_mean", "gsplat_mean", "delta_mean", "delta_sd",
                        "delta_se", "delta_min"])
    payload = {"files": [f for f, _ in payloads], "marks": marks, "rows": rows, "summary": stats}
    print(f"\nwrote {write_json(args.name, payload)}")
    return payload


if __name__ == "__main__":
    sys.exit(main() and 0)
