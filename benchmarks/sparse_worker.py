"""benchmarks/sparse.py's two kinds of worker process: a scene's depth prior, and one training run scored on the
protocol's test views (with the capture's SfM depth where there is one). Each writes its JSON atomically."""
from __future__ import annotations

import json
import platform
import shlex
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

import ablation
from sparse_data import REFERENCE_FILE, read_reference_depth
from sparse_runs import (Run, SceneSpec, load, needs_prior, prior_folder, run_budget, run_file,
                         run_steps)
from sparse_tables import SETTINGS

from warpgs.utils.atomic_file import atomic_write_bytes

def make_prior(args, scene: SceneSpec) -> dict:
    """The prior of one scene's training views, written to <out>/priors/...; prior.json (last) marks it done."""
    from warpgs.data import compute_depth_priors
    from warpgs.train.setup import plane_sweep

    folder = prior_folder(Path(args.out), args.tag, scene)
    loaded = load(scene, args.proto)
    start = time.perf_counter()
    _, report = compute_depth_priors(loaded, plane_sweep(None), out_dir=folder)
    report["seconds_total"] = round(time.perf_counter() - start, 1)
    report["device"] = args.device
    report["downscale"] = scene.downscale  # the folder's name leaves it out: prior_done checks it
    atomic_write_bytes(folder / "prior.json", json.dumps(report, indent=1, default=str).encode())
    return report


def reference_source(scene: SceneSpec) -> Optional[str]:
    """Where the test views' depth reference comes from: sparse_data.py's file, else the capture's sparse/0, else
    None."""
    if (scene.path / REFERENCE_FILE).is_file():
        return REFERENCE_FILE
    if (scene.path / "sparse" / "0" / "points3D.bin").is_file():
        return "sparse/0"
    return None


def reference_depth(scene: SceneSpec, loaded, views=None) -> tuple[Optional[dict], str]:
    """({view name: [H, W] sparse depth} for `views` (default: the test views), where it came from) or (None, why
    not)."""
    views = list(loaded.test if views is None else views)
    names = [loaded.names[v] for v in views]
    w, h = loaded.cameras[0].width, loaded.cameras[0].height
    source = reference_source(scene)
    if source == REFERENCE_FILE:
        return read_reference_depth(scene.path, names, w, h), REFERENCE_FILE
    if source == "sparse/0":
        from warpgs.data.depth.reference_points import sparse_depth_map, view_reference_points
        from warpgs.data.errors import SceneError

        try:
            points, per_view = view_reference_points(loaded)
        except SceneError as e:
            return None, f"sparse/0 unusable: {e}"
        return {loaded.names[v]: sparse_depth_map(loaded.cameras[v], points.xyz[per_view[v]])
                for v in views}, "sparse/0"
    return None, "no SfM model"


def train_one(args, run: Run) -> dict:
    """One training run, scored on the protocol's test views; its JSON is written atomically."""
    import torch

    label, preset, setting_overrides, own_marr = SETTINGS[run.setting]
    marr = {**args.marr_settings, **own_marr}  # --marr for every run; the setting's own keys win
    if args.threads:
        torch.set_num_threads(args.threads)
    loaded = load(run.scene, args.proto)
    reference, reference_from = reference_depth(run.scene, loaded)
    steps, budget = run_steps(args), run_budget(args)
    base = ([f"data.path={run.scene.path}", *args.proto.data_overrides(), f"data.downscale={run.scene.downscale}"]
            + ([f"strategy.max_primitives={budget}"] if budget else []))
    extra = (ablation.setting_overrides_for_run(preset, setting_overrides, budget, base + list(args.overrides))
             + ([f"data.depth_priors={prior_folder(Path(args.out), run.protocol, run.scene)}"]
                if needs_prior(run, args.overrides) else []))
    schedule = ablation.run_schedule(steps, real=True)
    with tempfile.TemporaryDirectory(prefix="warpgs-sparse-") as tmp:
        result = ablation.run_setting(run.setting, preset, steps, run.seed, args.device, extra, Path(tmp), args.pairs,
                                      schedule, marr, reference)
    payload = {"id": run.id, "protocol": run.protocol, "scene": run.scene.name, "scene_path": str(run.scene.path),
               "downscale": run.scene.downscale, "n_train": args.proto.n_train, "setting": run.setting,
               "label": label, "size": [loaded.cameras[0].width, loaded.cameras[0].height],
               "train": [loaded.names[v] for v in loaded.train], "train_index": loaded.train,
               "test": [loaded.names[v] for v in loaded.test], "test_index": loaded.test,
               "reference": reference_from, "device": args.device, "budget": budget,
               "command": shlex.join([sys.executable, *sys.argv]),  # this worker, as its driver started it
               "schedule_overrides": schedule,
               "torch_threads": torch.get_num_threads(), "machine": platform.node(),
               "gpu": torch.cuda.get_device_name() if args.device.startswith("cuda") else None, **result}
    atomic_write_bytes(run_file(Path(args.out), run), json.dumps(payload, indent=1).encode())
    return payload
