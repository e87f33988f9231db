"""benchmarks/sparse.py --along: each setting's held-out PSNR along its runs (mean ± standard error over seeds at
every step the runs were scored: eval.every's periodic scores and the final one), per scene. How long a protocol
should train is read from this table: on the 360° captures at 24 views 3DGS stops gaining by step 4000-6000 while
the sparse preset's mean is level from 4000 to 10k (docs/sparse_view.md; train.steps=by_views)."""
from __future__ import annotations

from common import fmt, mean_se


def scores_along(run: dict) -> dict:
    """{step: PSNR} of one run: its history's scores and, unless it was tabulated at an earlier step, the final."""
    points = {h["step"]: h["psnr"] for h in run.get("history") or []}
    if run.get("scored_at_step") is None:
        points[run["steps"]] = run["psnr"]
    return points


def along_runs(results: list[dict], settings: list[str]) -> dict:
    """{scene: {setting: {step: (mean, se)}}} over the steps every seed of that scene and setting was scored at."""
    by_scene: dict = {}
    for r in results:
        by_scene.setdefault(r["scene"], {}).setdefault(r["setting"], []).append(scores_along(r))
    along = {}
    for scene, runs in sorted(by_scene.items()):
        along[scene] = {}
        for key in [k for k in settings if k in runs]:
            steps = sorted(set.intersection(*(set(p) for p in runs[key])))
            along[scene][key] = {step: mean_se([p[step] for p in runs[key]]) for step in steps}
    return along


def print_along(along: dict, labels: dict) -> None:
    """One table: a row per scene and setting, a column per step."""
    steps = sorted({s for rows in along.values() for row in rows.values() for s in row})
    print("\nHeld-out PSNR along the runs (mean ± standard error over seeds)\n")
    print("| scene | setting | " + " | ".join(str(s) for s in steps) + " |")
    print("|---|---|" + "---|" * len(steps))
    for scene, rows in along.items():
        for key, row in rows.items():
            cells = [fmt(*row[s], 2) if s in row else "" for s in steps]
            print(f"| {scene} | {labels.get(key, key)} | " + " | ".join(cells) + " |")
