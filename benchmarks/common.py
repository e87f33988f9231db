"""Shared helpers for the benchmark scripts: timing, the standard scenes, result files, real-capture configs."""
from __future__ import annotations

import json
import math
import os
import socket
import statistics
import sys
import time
from pathlib import Path
from typing import Optional

import torch

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"


def standard_scenes_module():
    """../shared/bench/scenes.py (the scenes every speed figure is taken on); WARPGS_BENCH_SCENES overrides."""
    here = os.environ.get("WARPGS_BENCH_SCENES", str(ROOT.parent / "shared" / "bench"))
    if not (Path(here) / "scenes.py").exists():
        raise SystemExit(f"scenes.py not found in {here}: set WARPGS_BENCH_SCENES to the folder holding it")
    sys.path.insert(0, here)
    import scenes

    return scenes


def capture_config(data, *, device: str, steps: int, seed=None, eval_every: int = 0, config: str = "gaussians",
                   downscale=None, overrides=()):
    """The config a real-capture benchmark trains with: DIR with its LLFF split (every 8th view held out), quiet
    (no progress line, periodic checkpoints, saved images or LPIPS), then the user's key=value overrides, then
    data.downscale when given. seed None keeps the config's."""
    from warpgs.cli.commands import resolve_config_source
    from warpgs.config.loader import load_config

    items = [f"data.path={Path(data).resolve()}", "data.split=llff", f"train.device={device}",
             *([f"train.seed={seed}"] if seed is not None else []), f"train.steps={steps}", f"eval.every={eval_every}",
             "train.progress=false", "train.checkpoint_every=0", "eval.save_images=false", "eval.lpips=false",
             *overrides]
    if downscale:
        items.append(f"data.downscale={downscale}")
    return load_config(resolve_config_source(config), items)


def sync(device) -> None:
    """Wait for the GPU (device: a name or a torch.device); nothing on the CPU."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def time_call(fn, device: str, warmup: int = 2, repeats: int = 5) -> float:
    """Median wall time of fn() in milliseconds, synchronising the GPU around each call."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def run_host(device: str) -> dict:
    """Where a run ran, for pairing timings: host name, GPU name and UUID (None on the CPU), and the host's 1-minute
    load per core when it ended (other processes on the host slow a host-bound training step)."""
    gpu = uuid = None
    if str(device).startswith("cuda") and torch.cuda.is_available():
        index = torch.device(device).index
        index = torch.cuda.current_device() if index is None else index
        gpu = torch.cuda.get_device_name(index)
        uuid = str(getattr(torch.cuda.get_device_properties(index), "uuid", "")) or None
    return {"hostname": socket.gethostname(), "gpu": gpu, "gpu_uuid": uuid,
            "load_per_core": round(os.getloadavg()[0] / (os.cpu_count() or 1), 3)}


def write_json(name: str, payload: dict) -> Path:
    """Atomically writes benchmarks/results/<name>.json (or $OUT/<name>.json when OUT is set)."""
    folder = Path(os.environ["OUT"]) if os.environ.get("OUT") else RESULTS
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(payload, indent=2))
    os.replace(tmp, path)
    return path


def read_results(files, what: str) -> list:
    """[(file, payload)] of result JSON files; a file that cannot be read or parsed stops the run, named."""
    payloads = []
    for f in files:
        try:
            payloads.append((f, json.loads(Path(f).read_text())))
        except (OSError, json.JSONDecodeError) as e:
            raise SystemExit(f"{f}: not a readable {what} ({e})")
    return payloads


def asks_auto_steps(overrides) -> bool:
    """Whether key=value overrides ask for train.steps=auto (aliases expanded as the config does, any case): a run
    whose rule ends it within the bound it was given, so its step count is its own."""
    from warpgs.config.loader import parse_override

    for item in overrides or ():
        key, value = parse_override(str(item))
        if key == "train.steps" and str(value).strip().lower() == "auto":
            return True
    return False


def stopped_by_rule(run: dict) -> bool:
    """Whether a run file's step count was the run's own (made with train.steps=auto, asks_auto_steps)."""
    return asks_auto_steps(run.get("overrides"))


def mean_se(values: list) -> tuple[Optional[float], Optional[float]]:
    """(mean, standard error of the mean) of the values that are numbers (None and NaN left out); (None, None) for
    none, and a None error for one."""
    vals = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    if not vals:
        return None, None
    return statistics.fmean(vals), (statistics.stdev(vals) / math.sqrt(len(vals)) if len(vals) > 1 else None)


def fmt(m: Optional[float], se: Optional[float], digits: int, sign: bool = False) -> str:
    """"m ± se" with `digits` decimals (a sign with sign=True); "n/a" without a mean, no "±" without an error."""
    if m is None:
        return "n/a"
    return f"{m:{'+' if sign else ''}.{digits}f}" + (f" ± {se:.{digits}f}" if se is not None else "")


def print_table(rows: list[dict], columns: list[str]) -> None:
    widths = [max(len(c), *(len(_fmt(r.get(c))) for r in rows)) for c in columns]
    print(" | ".join(c.ljust(w) for c, w in zip(columns, widths)))
    print("-|-".join("-" * w for w in widths))
    for r in rows:
        print(" | ".join(_fmt(r.get(c)).ljust(w) for c, w in zip(columns, widths)))


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e-2 or abs(v) >= 1e4 else f"{v:.3f}"
    return str(v)
