"""One refine, two strategies, the same state: warpgs's DensifyStrategy.refine against gsplat's DefaultStrategy
(_grow_gs then _prune_gs) on the model and statistics the Trainer holds just before its refine at --step. Runs on
the CPU; only gsplat's Python sources are needed (--gsplat-src, as benchmarks/strategy_compare.py).

    python benchmarks/refine_compare.py data/beer --downscale 8 --seed 2 --step 700 --gsplat-src /path/to/gsplat-1.5.3

By default the opacity resets and the start of size pruning move to every 600 steps (strategy.reset_every=600
strategy.size_prune_start=600), so that a refine early in training exercises every rule: growth, the opacity rule
and the world-size rule. Reports how many primitives each side cloned, split and pruned, and the largest difference
between the two results' rows other than the split children's positions (which come from random draws), matched
after sorting. Writes refine_compare_<name>.json.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from common import ROOT, capture_config, import_gsplat_python, write_json

sys.path.insert(0, str(ROOT))

from warpgs.train.trainer import Trainer  # noqa: E402

EARLY_RULES = ["strategy.reset_every=600", "strategy.size_prune_start=600"]
COMPARED = (("log_scales", "scales"), ("logit_opacities", "opacities"), ("quats", "quats"), ("sh0", "sh0"),
            ("shN", "shN"))  # (warpgs name, gsplat name): everything but the means


def trainer_before_refine(args):
    """(trainer after the refine at args.step, the model parameters and statistics just before it)."""
    cfg = capture_config(args.data, device="cpu", steps=args.steps, seed=args.seed, downscale=args.downscale,
                         overrides=[*(EARLY_RULES if not args.keep_schedule else []), *args.overrides])
    cfg.output.dir = args.out
    trainer = Trainer(cfg, quiet=True)
    strategy, before = trainer.strategy, {}
    refine = strategy.refine

    def snapshot_then_refine(model, optimizers, step):
        if step == args.step:
            before["params"] = {k: v.detach().clone() for k, v in model.params.items()}
            before["grad"], before["count"] = strategy.grad_accum.clone(), strategy.count.clone()
        return refine(model, optimizers, step)

    strategy.refine = snapshot_then_refine
    report = None
    while trainer.step <= args.step:
        info = trainer.train_step()
        report = info["densify"] or report
    if "params" not in before:
        raise SystemExit(f"--step {args.step}: no refine ran there (refines run every "
                         f"{cfg.strategy.refine_every} steps after {cfg.strategy.refine_start})")
    return trainer, before, report


def gsplat_refine(trainer, before, step: int):
    from gsplat.strategy import DefaultStrategy

    s, strategy = trainer.config.strategy, trainer.strategy
    p = before["params"]
    params = torch.nn.ParameterDict({"means": p["means"], "scales": p["log_scales"], "quats": p["quats"],
                                     "opacities": p["logit_opacities"], "sh0": p["sh0"], "shN": p["shN"]})
    optimizers = {k: torch.optim.Adam([{"params": [params[k]], "lr": 1e-3, "name": k}]) for k in params}
    # gsplat measures both the clone/split size and the world-size rule against one scene scale; ours measures the
    # world-size rule against world_extent: scale prune_scale3d so that both rules compare with the same length.
    gs = DefaultStrategy(prune_opa=s.prune_opacity, grow_grad2d=s.grad_threshold, grow_scale3d=s.dense_scale,
                         prune_scale3d=s.prune_world_scale * strategy.world_extent / strategy.scene_extent,
                         refine_start_iter=s.refine_start, refine_stop_iter=s.refine_stop,
                         refine_every=s.refine_every, reset_every=s.size_prune_start)
    state = {"grad2d": before["grad"].clone(), "count": before["count"].float(), "scene_scale": strategy.scene_extent,
             "radii": None}
    duplicated, split = gs._grow_gs(params, optimizers, state, step)
    pruned = gs._prune_gs(params, optimizers, state, step)
    return {"cloned": int(duplicated), "split": int(split), "pruned": int(pruned)}, params


def sorted_rows(tensors) -> np.ndarray:
    m = torch.cat([t.detach().reshape(len(t), -1) for t in tensors], 1).numpy()
    return m[np.lexsort(m.T[::-1])]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="scene folder (COLMAP, transforms.json or LLFF)")
    ap.add_argument("--downscale", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--step", type=int, default=700, help="the refine step to compare (a multiple of refine_every)")
    ap.add_argument("--steps", type=int, default=5000, help="train.steps (sets the learning-rate schedule)")
    ap.add_argument("--keep-schedule", action="store_true", help="keep the config's reset and size-pruning steps")
    ap.add_argument("--gsplat-src", default=None, help="folder holding gsplat's Python package (gsplat/)")
    ap.add_argument("overrides", nargs="*", help="key=value config overrides")
    args = ap.parse_intermixed_args(argv)
    import_gsplat_python(args.gsplat_src, "gsplat.strategy", "strategy")
    with tempfile.TemporaryDirectory() as tmp:
        args.out = tmp
        trainer, before, ours_report = trainer_before_refine(args)
        theirs, gs_params = gsplat_refine(trainer, before, args.step)
    ours = trainer.model.params
    same_shape = len(ours["means"]) == len(gs_params["means"])
    row_diff = None
    if same_shape:
        a = sorted_rows([ours[w] for w, _ in COMPARED])
        b = sorted_rows([gs_params[g] for _, g in COMPARED])
        row_diff = float(np.abs(a - b).max())
    mine = {k: ours_report[k] for k in ("cloned", "split", "pruned", "num_primitives", "pruned_by")}
    print(f"step {args.step}, {len(before['params']['means'])} primitives before")
    print(f"  warpgs: cloned {mine['cloned']}, split {mine['split']}, pruned {mine['pruned']} -> "
          f"{mine['num_primitives']} (by rule {mine['pruned_by']})")
    print(f"  gsplat: cloned {theirs['cloned']}, split {theirs['split']}, pruned {theirs['pruned']} -> "
          f"{len(gs_params['means'])}")
    print("  rows other than the means, sorted: " + (f"largest difference {row_diff:.3g}" if same_shape
                                                        else "different counts, not compared"))
    payload = {"data": args.data, "downscale": args.downscale, "seed": args.seed, "step": args.step,
               "warpgs": mine, "gsplat": dict(theirs, num_primitives=len(gs_params["means"])),
               "max_row_difference_except_means": row_diff, "command": " ".join(sys.argv)}
    name = f"refine_compare_{Path(args.data).resolve().name}_s{args.seed}_step{args.step}"
    print(f"wrote {write_json(name, payload)}")
    return payload


if __name__ == "__main__":
    main()
