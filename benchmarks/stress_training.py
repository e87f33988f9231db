"""Numerical stability of real training over a long run: configs/stress.yaml (10x learning rates, SH degree 3
from step 0, densification every 10 steps up to the budget, frequent opacity resets, near plane 1e-4, random
init with a far shell) through the public Trainer API, with the NaN guard on.

    python benchmarks/stress_training.py --steps 200                          # CPU smoke check (~1 min)
    python benchmarks/stress_training.py --device cuda                        # 5000 steps at 128x96
    python benchmarks/stress_training.py --device cuda --steps 30000 --seed 1 --set strategy.max_primitives=200000

Every --interval steps it records: steps done, loss (last, mean and max over the interval), number of
primitives, refine passes and opacity resets in the interval, max |value| of each parameter group (the learned
background included), and whether a non-finite loss, loss term or parameter appeared. A NonFiniteError stops the
run; the offending parameter (or loss term), its step and the step of the last good checkpoint are recorded.
Held-out PSNR/SSIM come from the trainer's final metrics (or, after a stop with finite parameters, from
evaluating the state it stopped in). Prints a table and writes benchmarks/results/stress_training_<device>.json
(or $OUT/...); training outputs (checkpoint, PLY, metrics.json) go to --out.
"""
from __future__ import annotations

import argparse
import math
import platform
import sys
import time

import torch

from common import ROOT, print_table, write_json

sys.path.insert(0, str(ROOT))

from warpgs.train.checkpoint import load_checkpoint  # noqa: E402
from warpgs.train.trainer import NonFiniteError, Trainer  # noqa: E402

SHORT = {"modules.environment.coeffs": "environment", "logit_opacities": "opacity_logit"}


def json_number(v: float):
    """JSON has no NaN/Inf: non-finite values are written as strings ("nan", "inf")."""
    return v if math.isfinite(v) else str(v)


def param_maxima(trainer) -> dict:
    """max |value| per parameter group (nan when a NaN is present; 0 for an empty group)."""
    out = {}
    with torch.no_grad():
        for name, p in trainer.named_parameters():
            if p.numel() == 0:
                out[name] = 0.0
            elif not bool(torch.isfinite(p).all()):
                out[name] = float("nan") if bool(torch.isnan(p).any()) else float("inf")
            else:
                out[name] = float(p.abs().max())
    return out


class IntervalRecorder:
    """Trainer callback: summarises every `interval` steps (and the partial interval a stop leaves)."""

    def __init__(self, interval: int):
        self.interval = interval
        self.rows: list = []
        self._reset()

    def _reset(self):
        self.losses, self.refines, self.resets, self.bad_terms = [], 0, 0, set()

    def __call__(self, trainer, step: int, info: dict) -> None:
        self.losses.append(info["loss"])
        self.bad_terms |= {k for k, v in info["values"].items() if not math.isfinite(v)}
        report = info.get("densify") or {}
        self.refines += "cloned" in report
        self.resets += bool(report.get("opacity_reset"))
        if trainer.step % self.interval == 0 or trainer.step == trainer.max_steps:
            self.flush(trainer)

    def flush(self, trainer) -> None:
        if not self.losses and self.rows and self.rows[-1]["step"] == trainer.step:
            return
        maxima = param_maxima(trainer)
        finite_losses = [v for v in self.losses if math.isfinite(v)]
        nonfinite = (len(finite_losses) < len(self.losses) or bool(self.bad_terms)
                     or not all(math.isfinite(v) for v in maxima.values()))
        self.rows.append({
            "step": trainer.step, "seconds": round(trainer.train_seconds, 2),
            "loss": json_number(self.losses[-1]) if self.losses else None,
            "loss_mean": sum(finite_losses) / len(finite_losses) if finite_losses else None,
            "loss_max": max(finite_losses) if finite_losses else None,
            "num_primitives": trainer.model.num_primitives, "refines": self.refines, "opacity_resets": self.resets,
            "max_abs": {name: json_number(v) for name, v in maxima.items()},
            "nonfinite": nonfinite, "nonfinite_terms": sorted(self.bad_terms)})
        self._reset()


def checkpoint_step(trainer):
    """The step of the checkpoint on disk (the last good one after a stop), or None."""
    try:
        return int(load_checkpoint(trainer.checkpoint_path)["step"])
    except (FileNotFoundError, ValueError):
        return None


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=5000)
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--width", type=int, default=128, help="built-in scene resolution (data.path null)")
    ap.add_argument("--height", type=int, default=96)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="training output folder (default outputs/stress_training_<device>)")
    ap.add_argument("--interval", type=int, default=100, help="record a row every this many steps")
    ap.add_argument("--config", default=str(ROOT / "configs" / "stress.yaml"))
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="extra config overrides")
    args = ap.parse_args()
    if args.steps < 1 or args.interval < 1:
        ap.error("--steps and --interval must be positive")

    out_dir = args.out or str(ROOT / "outputs" / f"stress_training_{args.device}")
    overrides = [f"train.steps={args.steps}", f"train.device={args.device}", f"train.seed={args.seed}",
                 f"data.width={args.width}", f"data.height={args.height}", f"output.dir={out_dir}",
                 "train.progress=false", *args.set,
                 "train.nan_guard=true"]  # last: the run is about what the guard catches
    recorder = IntervalRecorder(args.interval)
    t_wall = time.perf_counter()
    trainer = Trainer(args.config, overrides=overrides, callbacks=[recorder], quiet=True)
    initial = trainer.model.num_primitives
    stopped, crashed, final = None, None, {}
    try:
        result = trainer.fit()
        final = {k: result.metrics.get(k) for k in ("split", "psnr", "ssim", "num_primitives", "final_loss")}
        final["evals"] = result.history
    except NonFiniteError as e:
        recorder.flush(trainer)
        stopped = {"step": e.step, "name": e.name, "message": str(e),
                   "last_good_checkpoint_step": checkpoint_step(trainer)}
        if all(math.isfinite(v) for v in param_maxima(trainer).values()):  # a loss/gradient stop: state is usable
            m = trainer.evaluate()
            final = {"split": m["split"], "psnr_at_stop": m["psnr"], "ssim_at_stop": m["ssim"],
                     "num_primitives": trainer.model.num_primitives, "evals": trainer.history}
    except Exception as e:  # a crash is a finding too: record it, then let it propagate
        recorder.flush(trainer)
        crashed = {"step": trainer.step, "error": f"{type(e).__name__}: {e}"}
        raise
    finally:
        wall = time.perf_counter() - t_wall
        payload = {"config": args.config, "overrides": overrides, "device": args.device,
                   "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None,
                   "machine": platform.processor() or platform.machine(), "torch": torch.__version__,
                   "size": [args.width, args.height], "seed": args.seed, "steps_requested": args.steps,
                   "steps_done": trainer.step, "completed": stopped is None and crashed is None
                   and trainer.step == args.steps, "initial_primitives": initial, "wall_seconds": round(wall, 1),
                   "train_seconds": round(trainer.train_seconds, 1), "stopped": stopped, "crashed": crashed,
                   "final": final, "intervals": recorder.rows}
        path = write_json(f"stress_training_{args.device}", payload)

    groups = list(recorder.rows[0]["max_abs"]) if recorder.rows else []
    table = [{"step": r["step"], "loss": r["loss"], "loss_max": r["loss_max"], "prims": r["num_primitives"],
              "refines": r["refines"], "resets": r["opacity_resets"], "nonfinite": r["nonfinite"],
              **{SHORT.get(g, g): r["max_abs"][g] for g in groups}} for r in recorder.rows]
    print_table(table, ["step", "loss", "loss_max", "prims", "refines", "resets", *[SHORT.get(g, g) for g in groups],
                        "nonfinite"])
    if stopped:
        print(f"\nSTOPPED by the NaN guard at step {stopped['step']} on {stopped['name']!r}: {stopped['message']}; "
              f"last good checkpoint: step {stopped['last_good_checkpoint_step']}")
    else:
        print(f"\ncompleted {trainer.step} steps, {initial} -> {trainer.model.num_primitives} primitives")
    for key in ("psnr", "psnr_at_stop"):
        if final.get(key) is not None:
            print(f"held-out ({final['split']}) {key} {final[key]:.2f} dB, ssim "
                  f"{final.get('ssim', final.get('ssim_at_stop')):.4f}")
    print(f"train {trainer.train_seconds:.1f} s, wall {wall:.1f} s; wrote {path}")
    return 1 if stopped else 0


if __name__ == "__main__":
    sys.exit(main())
