"""Pool `raster.py --gsplat` results over processes: per primitive, size and resolution, the mean of each process's
warpgs / gsplat ratio (forward and forward+backward) and its standard error over the processes.

One process's per-round standard error says how steady that process was; a GPU's speed also moves between processes
and machine starts, so a ratio is quoted as the mean over several processes with the spread between them.

    python benchmarks/raster_pool.py OUT_NAME benchmarks/results/raster_cuda_h200_s45{a,b,c}.json \
        benchmarks/results/raster_cuda_h200_bwd_order_s43.json:raster_new_

A FILE is one raster.py result ({"meta", "rows"}) or a collection ({"runs": {name: result}}); FILE:PREFIX takes the
collection's runs whose names start with PREFIX. Prints a table and writes benchmarks/results/OUT_NAME.json (or
$OUT/OUT_NAME.json).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from common import mean_se, print_table, read_results, write_json

METRICS = ("ratio_fwd", "ratio_fwd_bwd", "fwd_ms", "fwd_bwd_ms", "gsplat_fwd_ms", "gsplat_fwd_bwd_ms")


def processes(spec: str) -> list[tuple[str, dict]]:
    """(name, raster.py result) for each process in FILE or FILE:PREFIX."""
    path, _, prefix = spec.partition(":")
    [(_, data)] = read_results([path], "raster.py result")
    if "rows" in data:
        return [(Path(path).name, data)]
    runs = data.get("runs")
    if not isinstance(runs, dict):
        raise SystemExit(f"{path}: neither a raster.py result (rows) nor a collection of them (runs)")
    picked = [(f"{Path(path).name}:{k}", v) for k, v in runs.items() if k.startswith(prefix) and "rows" in v]
    if not picked:
        raise SystemExit(f"{path}: no run whose name starts with {prefix!r}")
    return picked


def pool(specs: list[str]) -> list[dict]:
    groups: dict[tuple, dict] = {}
    for spec in specs:
        for name, result in processes(spec):
            for row in result["rows"]:
                if row.get("ratio_fwd") is None:
                    continue  # a row without gsplat beside it
                key = (row["primitive"], row["n"], row["resolution"])
                g = groups.setdefault(key, {"processes": [], **{k: [] for k in METRICS}})
                g["processes"].append(name)
                for k in METRICS:
                    g[k].append(float(row[k]))
    out = []
    for (primitive, n, resolution), g in sorted(groups.items()):
        row = {"primitive": primitive, "n": n, "resolution": resolution, "processes": len(g["processes"])}
        for k in METRICS:
            row[f"{k}_mean"], se = mean_se(g[k])
            if k.startswith("ratio"):
                row[f"{k}_se"] = se
        row["per_process"] = g
        out.append(row)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("name", help="output name (benchmarks/results/NAME.json)")
    ap.add_argument("files", nargs="+", help="raster.py result files; FILE:PREFIX picks runs of a collection")
    args = ap.parse_args()
    rows = pool(args.files)
    print_table(rows, ["primitive", "n", "resolution", "processes", "fwd_ms_mean", "gsplat_fwd_ms_mean", "ratio_fwd_mean",
                       "ratio_fwd_se", "fwd_bwd_ms_mean", "gsplat_fwd_bwd_ms_mean", "ratio_fwd_bwd_mean",
                       "ratio_fwd_bwd_se"])
    path = write_json(args.name, {"command": "python benchmarks/raster_pool.py " + " ".join([args.name] + args.files),
                                  "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
