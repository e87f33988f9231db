"""Held-out PSNR against training time on the dense synthetic scene (the built-in orbit: 31 training and 5
held-out views), for the warpgs trainer — and, with --gsplat, for a plain loop over gsplat's `rasterization`
and `DefaultStrategy` given the same data, initial points, view order, steps, learning rates and losses.

    python benchmarks/train.py                                     # CPU, configs/default.yaml (1500 steps)
    python benchmarks/train.py --steps 3000 --eval-every 250
    python benchmarks/train.py --device cuda --gsplat --size 512x384 --steps 7000 --config gaussians

Times are training time only (render, loss, backward, optimizer, densification; evaluation excluded), taken
with the GPU synchronised at each evaluation point. Prints a table and writes
benchmarks/results/train_<device>[_gsplat].json with every evaluation point and the time each system needs to
reach a few PSNR levels (and the ratio).

Differences left in the gsplat loop, on purpose or by necessity: gsplat's DefaultStrategy has no primitive
budget (ours stops densifying at strategy.max_primitives), samples split children with the global RNG, and
resets opacity to 2 x prune_opa; the size rules map to prune_scale3d (world) only; step 0 is not reported to
it. When the config enables the learned environment background (configs/default.yaml does), the gsplat loop
composites the same EnvironmentMap module behind its render, with the same learning rate.
"""
from __future__ import annotations

import argparse
import sys
import time

import torch

from common import ROOT, print_table, write_json

sys.path.insert(0, str(ROOT))

from warpgs.train.checkpoint import seed_everything  # noqa: E402
from warpgs.cli.commands import resolve_config_source  # noqa: E402
from warpgs.config.loader import load_config  # noqa: E402
from warpgs.metrics.image import psnr, ssim  # noqa: E402
from warpgs.train.optim import means_lr_at  # noqa: E402
from warpgs.train.trainer import Trainer  # noqa: E402
from warpgs.train import setup as train_setup  # noqa: E402


def sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def run_warpgs(cfg, eval_every: int) -> dict:
    trainer = Trainer(cfg, quiet=True)
    start = trainer.evaluate()
    points = [{"step": 0, "seconds": 0.0, "psnr": start["psnr"], "ssim": start["ssim"],
               "num_primitives": trainer.model.num_primitives}]
    t_wall = time.perf_counter()
    result = trainer.fit()
    wall = time.perf_counter() - t_wall
    for h in result.history:
        points.append({"step": h["step"], "seconds": h["train_seconds"], "psnr": h["psnr"], "ssim": h["ssim"],
                       "num_primitives": h["num_primitives"]})
    points.append({"step": result.steps, "seconds": round(result.train_seconds, 3), "psnr": result.metrics["psnr"],
                   "ssim": result.metrics["ssim"], "num_primitives": result.num_primitives})
    return {"system": "warpgs", "points": points, "wall_seconds": round(wall, 2),
            "final": {k: result.metrics[k] for k in ("psnr", "ssim", "num_primitives", "train_seconds")}}


def run_gsplat(cfg, eval_every: int) -> dict:
    """The plain loop: gsplat rasterization + DefaultStrategy, our data, init, losses, lrs and view order."""
    try:
        from gsplat import rasterization
        from gsplat.strategy import DefaultStrategy
    except ImportError as e:
        raise SystemExit(f"--gsplat: gsplat is not importable ({e}); pip install gsplat on the GPU machine")
    device = train_setup.resolve_device(cfg.train.device)
    scene = train_setup.load_training_scene(cfg.data)
    seed_everything(cfg.train.seed)
    model, _ = train_setup.build_model(scene, cfg, device)
    extent = train_setup.scene_extent(scene, cfg.train.scene_extent)
    background = train_setup.resolve_background(cfg.train.background, scene, device)
    o, s = cfg.optim, cfg.strategy
    params = torch.nn.ParameterDict({
        "means": model.params["means"].detach().clone(), "scales": model.params["log_scales"].detach().clone(),
        "quats": model.params["quats"].detach().clone(), "opacities": model.params["logit_opacities"].detach().clone(),
        "sh0": model.params["sh0"].detach().clone(), "shN": model.params["shN"].detach().clone()}).to(device)
    lrs = {"means": o.means_lr * extent, "scales": o.scales_lr, "quats": o.quats_lr, "opacities": o.opacities_lr,
           "sh0": o.sh0_lr, "shN": o.shN_lr}
    optimizers = {k: torch.optim.Adam([{"params": [params[k]], "lr": lr, "name": k}], eps=o.eps,
                                      betas=(o.beta1, o.beta2)) for k, lr in lrs.items()}
    env, env_opt, dirs = None, None, {}
    if "environment" in cfg.extensions:
        from warpgs.model.environment import EnvironmentMap, ray_directions

        opts = cfg.extensions["environment"]
        env = EnvironmentMap(opts.get("degree", 3), opts.get("init_color", 0.5)).to(device)
        env_opt = torch.optim.Adam(env.parameters(), lr=opts.get("lr", 0.01))
        background = torch.zeros(3, device=device)
    steps = cfg.train.steps
    strategy = DefaultStrategy(
        prune_opa=s.prune_opacity, grow_grad2d=s.grad_threshold, grow_scale3d=s.dense_scale,
        prune_scale3d=s.prune_world_scale if s.prune_world_scale > 0 else float("inf"),
        refine_start_iter=s.refine_start, refine_stop_iter=s.refine_stop, refine_every=s.refine_every,
        reset_every=s.reset_every if s.reset_every else steps + 1)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=extent)

    train_views = [scene.view(i, device) for i in scene.train]
    test_views = [scene.view(i, device) for i in (scene.test or scene.train)]
    gen = torch.Generator().manual_seed(int(cfg.train.seed))
    queue: list = []
    max_deg = model.max_sh_degree

    def render(v, deg, grad=True):
        k = (deg + 1) ** 2
        colors = torch.cat([params["sh0"], params["shN"][:, : k - 1]], 1)
        img, alpha, info = rasterization(params["means"], params["quats"], torch.exp(params["scales"]),
                                         torch.sigmoid(params["opacities"]), colors, v.viewmat[None], v.K[None],
                                         v.width, v.height, sh_degree=deg, packed=False,
                                         backgrounds=background[None], near_plane=cfg.train.near,
                                         far_plane=cfg.train.far)
        img = img[0]
        if env is not None:
            if v.name not in dirs:
                dirs[v.name] = ray_directions(v.viewmat, v.K, v.width, v.height)
            img = img + (1.0 - alpha[0]) * env(dirs[v.name])
        return img, info

    def evaluate(deg):
        with torch.no_grad():
            ps, ss = [], []
            for v in test_views:
                img = render(v, deg)[0].clamp(0, 1)
                ps.append(float(psnr(img, v.image)))
                ss.append(float(ssim(img, v.image)))
        return sum(ps) / len(ps), sum(ss) / len(ss)

    points = [{"step": 0, "seconds": 0.0, **dict(zip(("psnr", "ssim"), evaluate(0))),
               "num_primitives": len(params["means"])}]
    seconds = 0.0
    t_wall = time.perf_counter()
    for step in range(steps):
        sync(device)
        t0 = time.perf_counter()
        if not queue:
            queue = torch.randperm(len(train_views), generator=gen).tolist()
        v = train_views[queue.pop(0)]
        deg = train_setup.active_sh_degree(step, cfg, max_deg)
        optimizers["means"].param_groups[0]["lr"] = means_lr_at(step, o, extent, steps)
        img, info = render(v, deg)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss = 0.8 * (img - v.image).abs().mean() + 0.2 * (1.0 - ssim(img, v.image))
        loss.backward()
        for opt in list(optimizers.values()) + ([env_opt] if env_opt is not None else []):
            opt.step()
            opt.zero_grad(set_to_none=True)
        if step > 0:  # some gsplat releases reset opacities at step 0 (step % reset_every == 0); ours never does
            strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
        sync(device)
        seconds += time.perf_counter() - t0
        if (step + 1) % eval_every == 0 or step + 1 == steps:
            p, q = evaluate(deg)
            points.append({"step": step + 1, "seconds": round(seconds, 3), "psnr": p, "ssim": q,
                           "num_primitives": len(params["means"])})
    wall = time.perf_counter() - t_wall
    last = points[-1]
    return {"system": "gsplat", "points": points, "wall_seconds": round(wall, 2),
            "final": {"psnr": last["psnr"], "ssim": last["ssim"], "num_primitives": last["num_primitives"],
                      "train_seconds": last["seconds"]}}


def time_to(points: list, level: float):
    """Training seconds until the held-out PSNR first reaches `level` (linear between evaluation points)."""
    prev = None
    for p in points:
        if p["psnr"] >= level:
            if prev is None or p["psnr"] == prev["psnr"]:
                return p["seconds"]
            f = (level - prev["psnr"]) / (p["psnr"] - prev["psnr"])
            return prev["seconds"] + f * (p["seconds"] - prev["seconds"])
        prev = p
    return None


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="default", help="preset or YAML (default: configs/default.yaml)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", type=int, help="training steps (default: the config's)")
    ap.add_argument("--eval-every", type=int, default=250)
    ap.add_argument("--size", default="128x96", help="synthetic scene resolution WxH")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gsplat", action="store_true", help="also run the plain gsplat loop (CUDA only)")
    ap.add_argument("--out", default=None, help="output folder for the warpgs run (default: a temp folder)")
    ap.add_argument("overrides", nargs="*", help="extra key=value config overrides (both systems)")
    args = ap.parse_args(argv)
    if args.gsplat and not args.device.startswith("cuda"):
        raise SystemExit("--gsplat needs --device cuda (gsplat has no CPU rasterizer)")
    width, height = (int(v) for v in args.size.lower().split("x"))
    import tempfile

    out = args.out or tempfile.mkdtemp(prefix="warpgs-bench-train-")
    overrides = [f"train.device={args.device}", f"train.seed={args.seed}", f"eval.every={args.eval_every}",
                 "train.progress=false", "train.checkpoint_every=0", "eval.save_images=false", "eval.lpips=false",
                 f"data.width={width}", f"data.height={height}", f"output.dir={out}"]
    if args.steps:
        overrides.append(f"train.steps={args.steps}")
    cfg = load_config(resolve_config_source(args.config), overrides + list(args.overrides))
    if cfg.data.path is not None:
        raise SystemExit("this benchmark runs on the built-in synthetic scene (data.path must be null)")

    runs = [run_warpgs(cfg, args.eval_every)]
    if args.gsplat:
        runs.append(run_gsplat(cfg, args.eval_every))

    rows = [{"system": r["system"], "step": p["step"], "seconds": p["seconds"], "psnr": p["psnr"], "ssim": p["ssim"],
             "primitives": p["num_primitives"]} for r in runs for p in r["points"]]
    print(f"held-out PSNR vs training time: synthetic orbit {width}x{height}, {cfg.train.steps} steps, "
          f"budget {cfg.strategy.max_primitives}, device {args.device}")
    print_table(rows, ["system", "step", "seconds", "psnr", "ssim", "primitives"])
    finals = [r["final"]["psnr"] for r in runs]
    levels = sorted({round(v, 1) for v in (min(finals) - 3.0, min(finals) - 1.0, min(finals) - 0.25)})
    reach = {f"{lv:.1f}": {r["system"]: time_to(r["points"], lv) for r in runs} for lv in levels}
    print("\nseconds to reach held-out PSNR:")
    for lv, t in reach.items():
        cells = "  ".join(f"{k} {'-' if v is None else f'{v:.1f}'}" for k, v in t.items())
        ratio = ""
        if args.gsplat and all(v for v in t.values()):
            ratio = f"  (warpgs/gsplat = {t['warpgs'] / t['gsplat']:.2f})"
        print(f"  {lv} dB: {cells}{ratio}")
    payload = {"device": args.device, "size": [width, height], "steps": cfg.train.steps, "seed": args.seed,
               "config": cfg.to_dict(), "runs": runs, "time_to_psnr": reach,
               "torch_threads": torch.get_num_threads()}
    if args.device.startswith("cuda"):
        payload["gpu"] = torch.cuda.get_device_name()
    name = f"train_{torch.device(args.device).type}" + ("_gsplat" if args.gsplat else "")
    print(f"\nwrote {write_json(name, payload)}")
    return payload


if __name__ == "__main__":
    main()
