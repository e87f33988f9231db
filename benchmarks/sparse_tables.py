"""benchmarks/sparse.py's statistics and tables: per scene and setting the mean ± standard error over seeds, the
mean over scenes, and the per-term ablation beside the paper's Table 2."""
from __future__ import annotations

import math
import statistics

import ablation
from common import fmt, mean_se

SETTINGS = {key: (label, preset, overrides, marr) for key, label, preset, overrides, marr in ablation.REAL_SETTINGS}
TERMS = [f"wo_{t}" for t in ablation.REAL_TERMS]
# The paper's Table 2 (its 3x3 light-field protocol, 30k steps): PSNR, SSIM, LPIPS. Its abbreviations: DR depth,
# DGR depth gradient, LDR local depth, GOR opacity, GSR scale, GCR count.
PAPER_TABLE2 = {"baseline": ("3DGS", 21.13, 0.695, 0.248), "wo_depth": ("w/o DR", 21.79, 0.722, 0.228),
                "wo_depth_grad": ("w/o DGR", 22.00, 0.728, 0.222), "wo_depth_local": ("w/o LDR", 21.98, 0.728, 0.223),
                "wo_opacity": ("w/o GOR", 21.75, 0.723, 0.221), "wo_scale": ("w/o GSR", 22.03, 0.729, 0.221),
                "wo_count": ("w/o GCR", 21.97, 0.720, 0.224), "full": ("Ours", 22.11, 0.732, 0.218)}


def paired(runs: dict, key: str, ref: str, metric: str = "psnr") -> list[float]:
    """Per seed, `key`'s metric minus `ref`'s (the seeds both have)."""
    a, b = runs.get(key, {}), runs.get(ref, {})
    return [a[s][metric] - b[s][metric] for s in sorted(a) if s in b]


def worst_view_psnr(run: dict):
    """The run's lowest per-test-view PSNR (a view a floater covers drags it down while the mean hides it, as on
    figurine: docs/sparse_view.md); None for a run scored at an earlier step or without per-view scores."""
    if run.get("scored_at_step") is not None:
        return None
    values = [v["psnr"] for v in (run.get("per_view") or {}).values() if v.get("psnr") is not None]
    return min(values) if values else None


def summarise(results: list[dict], settings: list[str]) -> dict:
    """{scene: {setting: {metric: (mean, se)}, ...}} plus the mean over scenes, and the printed rows."""
    by_scene: dict = {}
    for r in results:
        by_scene.setdefault(r["scene"], {}).setdefault(r["setting"], {})[r["seed"]] = {
            **r, "worst_view_psnr": worst_view_psnr(r)}
    metrics = (("psnr", 2), ("worst_view_psnr", 2), ("ssim", 4), ("lpips", 3), ("depth_order", 3), ("abs_rel", 4),
               ("coverage", 3), ("num_primitives", 0), ("train_seconds", 0))
    scenes = {}
    for scene, runs in sorted(by_scene.items()):
        rows = {}
        for key in settings:
            if key not in runs:
                continue
            seeds = runs[key]
            row = {m: mean_se([seeds[s][m] for s in seeds]) for m, _ in metrics}
            row["seeds"] = sorted(seeds)
            row["d_psnr_vs_baseline"] = mean_se(paired(runs, key, "baseline")) if key != "baseline" else (None, None)
            row["d_psnr_vs_full"] = mean_se(paired(runs, key, "full")) if key != "full" else (None, None)
            rows[key] = row
        scenes[scene] = rows
    # Mean over the scenes that have the setting: the scene means averaged, their standard errors combined.
    overall = {}
    for key in settings:
        have = [scenes[s][key] for s in scenes if key in scenes[s]]
        if not have:
            continue
        row = {}
        for m in [m for m, _ in metrics] + ["d_psnr_vs_baseline", "d_psnr_vs_full"]:
            pairs = [r[m] for r in have if r[m][0] is not None]
            if not pairs:
                row[m] = (None, None)
                continue
            ses = [se for _, se in pairs if se is not None]
            row[m] = (statistics.fmean(v for v, _ in pairs),
                      math.sqrt(sum(se * se for se in ses)) / len(pairs) if len(ses) == len(pairs) else None)
        row["scenes"] = len(have)
        overall[key] = row
    return {"scenes": scenes, "mean": overall, "digits": dict(metrics)}


def print_tables(summary: dict, header: str) -> None:
    digits = summary["digits"]
    cols = [("PSNR ↑", "psnr"), ("Δ PSNR vs 3DGS", "d_psnr_vs_baseline"), ("worst view PSNR", "worst_view_psnr"),
            ("SSIM ↑", "ssim"), ("LPIPS ↓", "lpips"),
            ("AbsRel ↓", "abs_rel"), ("Depth order ↑", "depth_order"), ("Coverage", "coverage"),
            ("#Primitives", "num_primitives"), ("Train s", "train_seconds")]

    def table(title: str, rows: dict) -> None:
        used = [(h, k) for h, k in cols if any(r[k][0] is not None for r in rows.values())]
        print(f"\n{title}\n")
        print("| Setting | " + " | ".join(h for h, _ in used) + " |")
        print("|---|" + "---|" * len(used))
        for key, r in rows.items():
            cells = ["—" if (key, k) == ("baseline", "d_psnr_vs_baseline") else
                     fmt(*r[k], digits.get(k, 2), sign=k.startswith("d_")) for _, k in used]
            print(f"| {SETTINGS[key][0]} | " + " | ".join(cells) + " |")

    print(header)
    for scene, rows in summary["scenes"].items():
        seeds = sorted({s for r in rows.values() for s in r["seeds"]})
        table(f"{scene} (seeds {','.join(map(str, seeds))}; mean ± standard error over seeds)", rows)
    if len(summary["scenes"]) > 1:
        table(f"Mean over scenes ({len(summary['scenes'])}; a setting's mean covers the scenes that ran it)",
              summary["mean"])
    mean = summary["mean"]
    if "full" in mean and any(k in mean for k in TERMS):
        print("\nPer-term ablation beside the paper's Table 2 (paper: 3x3 light fields, 30k steps; ours: the mean "
              "above; Δ = the row minus Ours (full), ours paired by seed)\n")
        print("| Paper row | paper PSNR | paper Δ | paper SSIM | paper LPIPS | ours PSNR | ours Δ | ours SSIM | "
              "ours LPIPS |")
        print("|---|---|---|---|---|---|---|---|---|")
        paper_full = PAPER_TABLE2["full"][1]
        for key, (row, psnr, ssim, lp) in PAPER_TABLE2.items():
            ours = mean.get(key)
            cells = ([fmt(*ours["psnr"], 2), fmt(*ours["d_psnr_vs_full"], 2, sign=True) if key != "full" else "—",
                      fmt(*ours["ssim"], 3), fmt(*ours["lpips"], 3)] if ours else ["not run"] * 4)
            paper_delta = "—" if key == "full" else f"{psnr - paper_full:+.2f}"
            print(f"| {row} | {psnr:.2f} | {paper_delta} | {ssim:.3f} | {lp:.3f} | " + " | ".join(cells)
                  + " |")
