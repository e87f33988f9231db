"""Merge ablation results that ran as separate processes (one setting or one seed each, e.g. side by side on one
GPU) into one table: the runs of each setting are pooled over the files, means and the paired PSNR gain against
the baseline are computed as benchmarks/ablation.py does for a single process.

    python benchmarks/ablation_merge.py OUT_NAME ablation_horns_cuda_10000_s*_*.json

The files must agree on the scene, its split, the step count, the device and the budget; a setting's seed may
appear once only."""
from __future__ import annotations

import argparse
import sys

import ablation
from common import read_results, write_json

# What every merged file must share (the run-specific parts, seeds and settings, are pooled).
SHARED = ("steps", "device", "budget", "prior_fill", "prior_options")
MISSING = {"prior_fill": 0.0, "prior_options": {}}  # what a file from before the key existed meant
SHARED_DATA = ("scene", "train_index", "test_index", "size")


def merge(payloads: list[tuple[str, dict]]) -> dict:
    first_name, first = payloads[0]
    merged = {k: first.get(k, MISSING.get(k)) for k in SHARED}
    merged["merged_from"] = [name for name, _ in payloads]
    if "data" in first:
        merged["data"] = first["data"]
    merged["settings"] = {}
    for name, p in payloads:
        for k in SHARED:
            if p.get(k, MISSING.get(k)) != first.get(k, MISSING.get(k)):
                raise SystemExit(f"{name}: {k} is {p.get(k, MISSING.get(k))!r}, {first_name} has "
                                 f"{first.get(k, MISSING.get(k))!r}")
        for k in SHARED_DATA:
            if ("data" in p) != ("data" in first) or ("data" in p and p["data"].get(k) != first["data"].get(k)):
                raise SystemExit(f"{name}: data.{k} differs from {first_name}'s: not the same scene or split")
        for key, entry in p["settings"].items():
            target = merged["settings"].setdefault(key, {k: v for k, v in entry.items() if k not in ("runs", "mean")}
                                                   | {"runs": []})
            seeds = {r["seed"] for r in target["runs"]}
            for run in entry["runs"]:
                if run["seed"] in seeds:
                    raise SystemExit(f"{name}: setting {key!r} seed {run['seed']} is already in an earlier file")
                target["runs"].append(run)
    # Baseline first, so the table reads as benchmarks/ablation.py prints it.
    order = sorted(merged["settings"], key=lambda k: (k != "baseline", k != "full"))
    merged["settings"] = {k: merged["settings"][k] for k in order}
    merged["seeds"] = sorted({r["seed"] for e in merged["settings"].values() for r in e["runs"]})
    return merged


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("name", help="result file name (written to benchmarks/results/, or $OUT)")
    ap.add_argument("files", nargs="+", help="ablation JSON files written by benchmarks/ablation.py")
    args = ap.parse_args(argv)
    payloads = read_results(args.files, "ablation result")
    for f, payload in payloads:
        if "settings" not in payload:
            raise SystemExit(f"{f}: no 'settings' in it: not written by benchmarks/ablation.py")
    return write_table(args.name, merge(payloads))


def write_table(name: str, merged: dict) -> dict:
    """Means and paired gains of the merged settings, printed as ablation.py prints them and written as `name`."""
    rows = ablation.summarise_settings(merged["settings"])
    ablation.print_table(merged, rows)
    merged["table"] = rows
    print(f"\nwrote {write_json(name, merged)}", file=sys.stderr)
    return merged


if __name__ == "__main__":
    main()
