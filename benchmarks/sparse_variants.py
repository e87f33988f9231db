"""Compare `sparse.py` waves that differ by an override: per scene, each variant's held-out PSNR (mean ± standard
error over seeds) and its differences from reference variants, paired by seed; then the mean over scenes.

sparse.py names a run by protocol, scene, setting and seed, so the same setting with another override (say
`train.drop_rate=0.3`) runs into another `--out` folder (its `priors/` a link to the first's, so every variant reads
the same prior). This script puts those folders side by side:

    python benchmarks/sparse_variants.py sparse_llff3_cuda_1000_drop_rate_h200 --ref 0.1,3DGS \
        3DGS=/tmp/sp01/runs:baseline 0.1=/tmp/sp01/runs:preset 0.3=/tmp/sp03/runs:preset

LABEL=FOLDER:SETTING takes the run files in FOLDER whose setting is SETTING; a label given twice gathers both folders
(e.g. two scenes' waves). Every variant must cover the same scenes and seeds under the same protocol, split and
length. Prints a table and writes benchmarks/results/NAME.json (or $OUT/NAME.json) with every run's scores.
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from common import fmt, mean_se, stopped_by_rule, write_json

METRICS = ("psnr", "ssim", "abs_rel", "num_primitives")
# What must agree between the variants' runs of one scene and seed for their difference to mean anything.
SAME = ("protocol", "n_train", "steps", "downscale", "size", "train_index", "test_index", "budget")


def load_variant(spec: str) -> tuple[str, dict]:
    """LABEL=FOLDER:SETTING -> (label, {(scene, seed): run})."""
    label, eq, rest = spec.partition("=")
    folder, colon, setting = rest.rpartition(":")
    if not (eq and colon and label and folder and setting):
        raise SystemExit(f"{spec!r}: expected LABEL=FOLDER:SETTING")
    runs = {}
    for f in sorted(Path(folder).glob("*.json")):
        run = json.loads(f.read_text())
        if run.get("setting") == setting:
            run["file"] = str(f)
            runs[(run["scene"], run["seed"])] = run
    if not runs:
        raise SystemExit(f"{spec}: no run files with setting {setting!r} in {folder}")
    return label, runs


def auto_steps_fit(a: dict, b: dict) -> bool:
    """Whether two runs' step counts may differ: one or both stopped by train.steps=auto's rule, and such a run no
    longer than a fixed-length one beside it (an auto run bounded at 30k is not a variant of a 10k run)."""
    a_auto, b_auto = stopped_by_rule(a), stopped_by_rule(b)
    if a_auto == b_auto:
        return a_auto  # both stopped by the rule, or both fixed (whose counts must match)
    auto, fixed = (a, b) if a_auto else (b, a)
    return auto.get("steps", 0) <= fixed.get("steps", 0)


def check_alike(variants: dict) -> list[tuple[str, int]]:
    """The (scene, seed) keys every variant has; an error naming the files when two runs differ in their set-up."""
    keys = [set(runs) for runs in variants.values()]
    common = set.intersection(*keys)
    if any(k != common for k in keys):
        missing = {label: sorted(common ^ set(runs)) for label, runs in variants.items() if set(runs) != common}
        raise SystemExit(f"the variants do not cover the same scenes and seeds: {missing}")
    first = next(iter(variants.values()))
    for key in sorted(common):
        for runs in variants.values():
            for field in SAME:
                if field == "steps" and auto_steps_fit(runs[key], first[key]):
                    continue  # train.steps=auto: the run ended where its rule said, within the other's length
                if runs[key].get(field) != first[key].get(field):
                    raise SystemExit(f"{runs[key]['file']} and {first[key]['file']} differ in {field!r}: "
                                     f"{runs[key].get(field)!r} against {first[key].get(field)!r}")
    return sorted(common)


def shared_overrides(runs) -> list:
    """The config overrides every run of a variant was made with (the scene's own path and priors differ)."""
    lists = [r.get("overrides") or [] for r in runs]
    return [o for o in lists[0] if all(o in other for other in lists[1:])]


def compare(variants: dict, refs: list[str]) -> dict:
    keys = check_alike(variants)
    scenes = sorted({scene for scene, _ in keys})
    seeds = sorted({seed for _, seed in keys})
    table = {}
    for scene in scenes:
        row = {}
        for label, runs in variants.items():
            mine = [runs[(scene, s)] for s in seeds]
            cell = {m: mean_se([r.get(m) for r in mine]) for m in METRICS}
            for ref in refs:
                cell[f"d_psnr_vs_{ref}"] = mean_se([r["psnr"] - variants[ref][(scene, r["seed"])]["psnr"] for r in mine])
            row[label] = cell
        table[scene] = row
    mean = {}
    for label, runs in variants.items():
        # Over seeds: each seed's mean over the scenes, then their spread; over scenes: the spread of scene means.
        per_seed = [statistics.fmean(runs[(sc, s)]["psnr"] for sc in scenes) for s in seeds]
        mean[label] = {"psnr": mean_se(per_seed),
                       "psnr_scenes_se": mean_se([table[sc][label]["psnr"][0] for sc in scenes])[1]}
        for ref in refs:
            per_seed_d = [statistics.fmean(runs[(sc, s)]["psnr"] - variants[ref][(sc, s)]["psnr"] for sc in scenes)
                          for s in seeds]
            mean[label][f"d_psnr_vs_{ref}"] = mean_se(per_seed_d)
            mean[label][f"d_psnr_vs_{ref}_scenes_se"] = mean_se(
                [table[sc][label][f"d_psnr_vs_{ref}"][0] for sc in scenes])[1]
        for m in METRICS[1:]:
            mean[label][m] = mean_se([table[sc][label][m][0] for sc in scenes])
    return {"refs": refs, "scenes": table, "mean": mean, "seeds": seeds}


def print_comparison(result: dict) -> None:
    labels = list(next(iter(result["scenes"].values())))
    refs = result["refs"]
    # A reference's difference from an earlier reference is the negative of the one printed: left out.
    deltas = [(label, ref) for ref in refs for label in labels
              if label != ref and not (label in refs and refs.index(label) > refs.index(ref))]

    print("| scene | " + " | ".join(labels) + " | " + " | ".join(f"Δ {a} vs {b}" for a, b in deltas) + " |")
    print("|---|" + "---|" * (len(labels) + len(deltas)))
    rows = list(result["scenes"].items()) + [("mean", result["mean"])]
    for scene, row in rows:
        print(f"| {scene} | " + " | ".join(fmt(*row[label]["psnr"], 2) for label in labels) + " | "
              + " | ".join(fmt(*row[a][f"d_psnr_vs_{b}"], 2, sign=True) for a, b in deltas) + " |")
    # The other scores, mean over the scenes (each scene's mean over seeds): what a results table quotes beside PSNR.
    print("\n| variant | SSIM | AbsRel | primitives |\n|---|---|---|---|")
    for label in labels:
        cell = result["mean"][label]
        prims = cell["num_primitives"][0]
        print(f"| {label} | {fmt(cell['ssim'][0], None, 3)} | {fmt(cell['abs_rel'][0], None, 3)} | "
              f"{'n/a' if prims is None else (f'{prims:.0f}' if prims < 10_000 else f'{prims / 1000:.0f}k')} |")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("name", help="output name (benchmarks/results/NAME.json)")
    ap.add_argument("variants", nargs="+", help="LABEL=FOLDER:SETTING, one per variant")
    ap.add_argument("--ref", required=True, help="comma-separated labels the differences are taken from")
    args = ap.parse_args(argv)
    variants: dict = {}
    for spec in args.variants:
        label, runs = load_variant(spec)
        mine = variants.setdefault(label, {})
        for key, run in runs.items():
            if key in mine:
                raise SystemExit(f"{label}: {run['file']} and {mine[key]['file']} are both {key[0]}, seed {key[1]}")
            mine[key] = run
    refs = args.ref.split(",")
    for ref in refs:
        if ref not in variants:
            raise SystemExit(f"--ref {ref!r}: not one of the labels {list(variants)}")
    result = compare(variants, refs)
    print_comparison(result)
    result["sources"] = args.variants
    result["overrides"] = {label: shared_overrides(runs.values()) for label, runs in variants.items()}
    result["runs"] = [{"variant": label, **{k: r.get(k) for k in ("scene", "seed", "file", "train_seconds") + METRICS}}
                      for label, runs in variants.items() for r in runs.values()]
    print(f"\nwrote {write_json(args.name, result)}")


if __name__ == "__main__":
    main()
