"""The two training loops the training benchmarks compare, on the same data, initial points, view order, steps,
learning rates and losses: the warpgs Trainer, and a plain loop over gsplat's `rasterization` and
`DefaultStrategy` (benchmarks/real_capture.py runs them on real captures). `warpgs_as_gsplat` puts warpgs's
rasterizer inside the gsplat loop, so that the loop and strategy can be told from the renderer.

Differences left in the gsplat loop, on purpose or by necessity: gsplat's DefaultStrategy has no primitive
budget (ours stops densifying at strategy.max_primitives), samples split children with the global RNG, and
resets opacity to 2 x prune_opa; the size rules map to prune_scale3d (world) only; step 0 is not reported to
it. gsplat 1.5.3's DefaultStrategy never resets opacities at all (its test `step % reset_every == 0 & step > 0`
is always false: `&` binds first; gsplat PR #776): where the installed release has that line, this loop applies
gsplat's own `reset_opa` on the reset steps, so both loops run the 3DGS recipe (`gsplat_reset="auto"`; "off"
keeps the release's behaviour). When the config enables the learned environment background, the gsplat loop composites the same
EnvironmentMap module behind its render, with the same learning rate.

Both loops record the primitive count after every step, so a refine step that deletes most of the model shows
(`largest_drop`).
"""
from __future__ import annotations

import time

import torch

from common import sync
from warpgs.losses.photometric import training_ssim
from warpgs.metrics.image import psnr, ssim
from warpgs.render.gaussians import rasterize
from warpgs.train import setup as train_setup
from warpgs.train.checkpoint import seed_everything
from warpgs.train.optim import means_lr_at
from warpgs.train.trainer import Trainer


def largest_drop(counts: list) -> dict:
    """The step whose primitive count fell the most, relative to the count before it. Entries are (step, count)
    or (step, count, {rule: primitives it pruned}); the rule counts of that step come along as "pruned_by"."""
    worst = {"step": None, "before": None, "after": None, "fraction_removed": 0.0, "pruned_by": None}
    for before, after in zip(counts, counts[1:]):
        (_, n0), (s1, n1) = before[:2], after[:2]
        if n0 > 0 and (n0 - n1) / n0 > worst["fraction_removed"]:
            worst = {"step": s1, "before": n0, "after": n1, "fraction_removed": round((n0 - n1) / n0, 4),
                     "pruned_by": after[2] if len(after) > 2 else None}
    return worst


def _record(counts: list, step: int, n: int, report) -> None:
    pruned_by = report.get("pruned_by") if report else None
    counts.append((step, n, pruned_by) if pruned_by is not None else (step, n))


def echo_point(system: str, step: int, seconds: float, psnr: float, primitives: int) -> None:
    """One evaluation as a log line when it happens: a run cut short (a GPU call's time limit) still leaves its
    marks in the log, and a detached run can be watched."""
    print(f"{system} evaluated at step {step}: {psnr:.3f} dB held-out, {primitives} primitives, "
          f"{seconds:.1f} s of training", flush=True)


def echo_evaluations(system: str = "warpgs"):
    """A Trainer callback that echoes each evaluation of its history once (the step after it ran: callbacks come
    before the loop's periodic evaluation)."""
    shown = [0]

    def callback(tr, step, info):
        for h in tr.history[shown[0]:]:
            echo_point(system, h["step"], h["train_seconds"], h["psnr"], h["num_primitives"])
        shown[0] = len(tr.history)
    return callback


def initial_model(cfg):
    """(the warpgs Trainer for `cfg`, a copy of its initial parameters that both loops start from, the list its
    per-step primitive counts are recorded into)."""
    counts: list = []
    trainer = Trainer(cfg, quiet=True,
                      callbacks=[lambda tr, step, info: _record(counts, step + 1, tr.model.num_primitives,
                                                                info.get("densify")), echo_evaluations()])
    counts.append((0, trainer.model.num_primitives))
    start = {k: v.detach().clone() for k, v in trainer.model.params.items()}
    return trainer, start, counts


def run_warpgs(trainer, counts: list, eval_every: int) -> dict:
    start = trainer.evaluate()
    points = [{"step": 0, "seconds": 0.0, "psnr": start["psnr"], "ssim": start["ssim"],
               "num_primitives": trainer.model.num_primitives}]
    t_wall = time.perf_counter()
    result = trainer.fit()
    wall = time.perf_counter() - t_wall
    for h in result.history:
        points.append({"step": h["step"], "seconds": h["train_seconds"], "psnr": h["psnr"], "ssim": h["ssim"],
                       "num_primitives": h["num_primitives"]})
    if points[-1]["step"] != result.steps:
        points.append({"step": result.steps, "seconds": round(result.train_seconds, 3),
                       "psnr": result.metrics["psnr"], "ssim": result.metrics["ssim"],
                       "num_primitives": result.num_primitives})
    final = {k: result.metrics[k] for k in ("psnr", "ssim", "num_primitives", "train_seconds", "steps")}
    if result.metrics.get("lpips") is not None:
        final["lpips"] = result.metrics["lpips"]
    if "speculative_pairs" in result.metrics:  # renders sized from earlier counts, and the steps skipped for it
        final["speculative_pairs"] = result.metrics["speculative_pairs"]
    out = {"system": "warpgs", "points": points, "wall_seconds": round(wall, 2), "final": final,
           "largest_drop": largest_drop(counts)}
    if "schedule" in result.metrics:  # train.steps=auto: its decisions and validation scores
        out["schedule"] = result.metrics["schedule"]
    out["stage_seconds"] = result.metrics["stage_seconds"]  # the wall beyond training: loading, compiling, validating
    return out


def gsplat_skips_opacity_reset() -> bool:
    """True when the installed gsplat's DefaultStrategy has the reset test that never fires (1.5.3)."""
    import inspect

    from gsplat.strategy import DefaultStrategy

    return "== 0 & step > 0" in inspect.getsource(DefaultStrategy.step_post_backward)


def run_gsplat(cfg, eval_every: int, scene, start: dict, gsplat_reset: str = "auto", *, rasterization=None,
               system: str = "gsplat") -> dict:
    """The plain loop: gsplat rasterization + DefaultStrategy on `scene`, from the initial parameters `start`
    (the warpgs model's), with our losses, learning rates and view order. gsplat_reset: "auto" applies the opacity
    resets a DefaultStrategy skips (see the module doc), "off" leaves the installed release as it is.
    rasterization: a stand-in with gsplat's signature (`warpgs_as_gsplat`: warpgs's renderer in gsplat's loop);
    system: the run's name in the result."""
    try:
        if rasterization is None:
            from gsplat import rasterization
        from gsplat.strategy import DefaultStrategy
        from gsplat.strategy.ops import reset_opa
    except ImportError as e:
        raise SystemExit(f"--gsplat: gsplat is not importable ({e}); pip install gsplat on the GPU machine")
    if gsplat_reset not in ("auto", "off"):
        raise ValueError(f"gsplat_reset: expected 'auto' or 'off', got {gsplat_reset!r}")
    manual_reset = gsplat_reset == "auto" and bool(cfg.strategy.reset_every) and gsplat_skips_opacity_reset()
    if manual_reset:
        print("gsplat loop: this gsplat's DefaultStrategy never resets opacities (gsplat PR #776); the loop applies "
              "gsplat's reset_opa on the reset steps", flush=True)
    device = train_setup.resolve_device(cfg.train.device)
    train_setup.install_training_ssim(cfg.train.fused_ssim, device)  # the D-SSIM the warpgs run of `cfg` trains with
    seed_everything(cfg.train.seed)
    extent = train_setup.scene_extent(scene, cfg.train.scene_extent)
    background = train_setup.resolve_background(cfg.train.background, scene, device)
    o, s = cfg.optim, cfg.strategy
    params = torch.nn.ParameterDict({
        "means": start["means"].clone(), "scales": start["log_scales"].clone(), "quats": start["quats"].clone(),
        "opacities": start["logit_opacities"].clone(), "sh0": start["sh0"].clone(),
        "shN": start["shN"].clone()}).to(device)
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
    if not isinstance(steps, int):  # "auto" and "by_views" are resolved by warpgs's Trainer only
        raise ValueError(f"train.steps: gsplat's loop needs a fixed step count, got {steps!r}")
    strategy = DefaultStrategy(
        prune_opa=s.prune_opacity, grow_grad2d=s.grad_threshold, grow_scale3d=s.dense_scale,
        prune_scale3d=s.prune_world_scale if s.prune_world_scale > 0 else float("inf"),
        refine_start_iter=s.refine_start, refine_stop_iter=s.refine_stop, refine_every=s.refine_every,
        reset_every=s.reset_every if s.reset_every else steps + 1, absgrad=s.absgrad)  # strategy.absgrad: both
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=extent)

    train_views = [scene.view(i, device) for i in scene.train]
    test_views = [scene.view(i, device) for i in (scene.test or scene.train)]
    gen = torch.Generator().manual_seed(int(cfg.train.seed))
    queue: list = []
    max_deg = cfg.model.sh_degree
    counts = [(0, len(params["means"]))]

    def render(v, deg, grad=True):
        k = (deg + 1) ** 2
        colors = torch.cat([params["sh0"], params["shN"][:, : k - 1]], 1)
        img, alpha, info = rasterization(params["means"], params["quats"], torch.exp(params["scales"]),
                                         torch.sigmoid(params["opacities"]), colors, v.viewmat[None], v.K[None],
                                         v.width, v.height, sh_degree=deg, packed=False,
                                         backgrounds=background[None], near_plane=cfg.train.near,
                                         far_plane=cfg.train.far, absgrad=s.absgrad)
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
        loss = 0.8 * (img - v.image).abs().mean() + 0.2 * (1.0 - training_ssim(img, v.image))  # the trainer's D-SSIM
        loss.backward()
        for opt in list(optimizers.values()) + ([env_opt] if env_opt is not None else []):
            opt.step()
            opt.zero_grad(set_to_none=True)
        rules = None
        if step > s.refine_start and step % s.refine_every == 0 and step < s.refine_stop:
            rules = gsplat_prune_rules(params, step, s, extent)  # what its refine will test (before growing)
        if step > 0:  # some gsplat releases reset opacities at step 0 (step % reset_every == 0); ours never does
            strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
            if manual_reset and step % s.reset_every == 0 and step < s.refine_stop:  # where gsplat meant to
                reset_opa(params=params, optimizers=optimizers, state=state, value=s.prune_opacity * 2.0)
        sync(device)
        seconds += time.perf_counter() - t0
        _record(counts, step + 1, len(params["means"]), {"pruned_by": rules} if rules else None)
        if (step + 1) % eval_every == 0 or step + 1 == steps:
            p, q = evaluate(deg)
            points.append({"step": step + 1, "seconds": round(seconds, 3), "psnr": p, "ssim": q,
                           "num_primitives": len(params["means"])})
            echo_point(system, step + 1, seconds, p, len(params["means"]))
    wall = time.perf_counter() - t_wall
    last = points[-1]
    return {"system": system, "points": points, "wall_seconds": round(wall, 2),
            "final": {"psnr": last["psnr"], "ssim": last["ssim"], "num_primitives": last["num_primitives"],
                      "train_seconds": last["seconds"]},
            "largest_drop": largest_drop(counts), "opacity_reset_applied_by_loop": manual_reset}


@torch.no_grad()
def gsplat_prune_rules(params, step: int, s, extent: float) -> dict:
    """Primitives gsplat's DefaultStrategy pruning rules flag at a refine step, counted before it grows: opacity
    under prune_opa, and after its first opacity reset the largest scale over prune_scale3d x scene scale."""
    low = torch.sigmoid(params["opacities"].flatten()) < s.prune_opacity
    big = torch.zeros_like(low)
    if s.prune_world_scale > 0 and s.reset_every and step > s.reset_every:
        big = torch.exp(params["scales"]).amax(-1) > s.prune_world_scale * extent
    return {"opacity": int(low.sum()), "world_size": int(big.sum())}


class _ScreenMeans:
    """What gsplat's strategy reads as info["means2d"]: .grad as [1, N, 2]; retain_grad() is a no-op because
    warpgs's means2d is a leaf that keeps its gradient anyway."""

    def __init__(self, leaf: torch.Tensor):
        self.leaf = leaf

    def retain_grad(self) -> None:
        pass

    @property
    def grad(self) -> torch.Tensor:
        return self.leaf.grad[None]

    @property
    def absgrad(self) -> torch.Tensor:  # gsplat's strategy with absgrad=True reads this
        return self.leaf.absgrad[None]


def warpgs_as_gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, sh_degree,
                     packed=False, backgrounds=None, near_plane=0.01, far_plane=1e10, absgrad=False):
    """gsplat's `rasterization` signature (one camera, packed=False) over warpgs.rasterize; the strategy counts a
    primitive as seen (its radii > 0) when it reaches a tile (`out.visible`)."""
    out = rasterize(means, quats, scales, opacities, colors, viewmats[0], Ks[0], width, height,
                    sh_degree=sh_degree, background=None if backgrounds is None else backgrounds[0],
                    outputs=("rgb", "alpha"), near=near_plane, far=far_plane, track_means2d=True, absgrad=absgrad)
    visible = out.visible.to(means.dtype)[None, :, None].expand(1, -1, 2)  # gsplat selects radii > 0
    info = {"means2d": _ScreenMeans(out.means2d), "radii": visible, "width": width, "height": height,
            "n_cameras": 1, "gaussian_ids": None}
    return out.rgb[None], out.alpha[None], info
