"""3DGS-style adaptive density control with a hard primitive budget.

Trainer contract, once per training step (step counts from 0):

    strategy = DensifyStrategy(StrategyConfig(...), scene_extent)
    strategy.initialize(model)                          # before step 0 (and after loading a checkpoint)
    out = rasterize(**model.render_inputs(), viewmat=V, K=K, width=W, height=H, ...)
    strategy.step_pre_backward(model, step)
    loss.backward()
    optimizer.step()                                    # grads are still there: only zero_grad clears them
    strategy.step_post_backward(model, optimizer, step, visible=out.visible, viewmat=V, K=K, width=W, height=H)
    optimizer.zero_grad(set_to_none=True)

`step_post_backward` needs, per rendered camera, `visible` ([N] bool, `RenderOutput.visible`), `viewmat`
[4,4], `K` [3,3], `width`, `height` (or batches [B,N], [B,4,4], [B,3,3]), and the loss gradient with
respect to each primitive's projected 2D mean:
  - `grad2d` [N,2] or [B,N,2] in pixel units (dL/d(pixel x, pixel y)) when the renderer exposes it;
  - otherwise (one camera only) it is recovered from `model.means.grad`: with p = R mu + t and the pinhole
    Jacobian J = d(mean2d)/dp, the 3D gradient is R^T J^T g2d plus the (smaller) terms through the
    covariance and the SH view direction; g2d = (J J^T)^-1 J R dL/dmu is the least-squares solution and is
    exact when the loss depends on the means only through their 2D positions.
Calling it after optimizer.step() (as above) means the densify step does not lose an Adam update; calling it
before works too (new Parameters then have no grad for that step, like 3DGS).

The same in pieces, for batches of views rendered one at a time (sizes may differ) and for data-parallel runs:
`observe(...)` per camera (views_in_loss = the global batch size), `merge_observations`, a reduction over the
ranks (sums of gradient norms and counts, maxima of radii: train/distributed.py), `add_observations`, then
`maybe_refine(model, optimizers, step)`. For one camera, step_post_backward is exactly observe + add +
maybe_refine.

The statistics themselves (`strategy.stats`, their units and how observations combine) are train/densify_stats.py.
The default threshold 0.0002 matches 3DGS for a loss on the same scale (0.8 L1 + 0.2 (1 - SSIM), means over pixels).

Screen radii (for screen-size pruning, so only when a screen rule is on; otherwise no radii are computed or kept,
and the observations carry None) are computed from the camera (screen_geometry.py): 3 sqrt(largest eigenvalue) of the
projected covariance with the 0.3 px^2 low-pass, as the projection kernel does (3D scales; surfels get 0 for
the third axis).

Size pruning is scale-aware (issue 12: a fixed 20 px screen rule deleted a 1080x1920 phone capture at the first
size-pruning step; a world rule against the cameras' radius does the same to captures whose cameras barely
move): the screen rule compares the radius with the image's larger side (`prune_screen_size`, a fraction, off by default as in gsplat; 3DGS's 20 px rule never fired, its
radii were zeroed before the test), and the world rule compares the largest scale with `world_extent`, which the
trainer computes from what the cameras see (warpgs/data/extent.py), not only from how far they move.
A refine step that removes more than half of the primitives issues a `PruningWarning` naming how many each rule
removed; every refine's report carries the same counts under "pruned_by".

When densification and resets happen over a run (the tail a fixed-step run leaves alone: `refine_stop_fraction`, a
reset only with a whole interval of training after it; `train.steps=auto`'s earlier stop) is train/schedule.py's
DensifySchedule (`strategy.schedule`); maybe_refine / step_post_backward do nothing outside its `densifying(step)`.

A refine grows before it prunes (3DGS and gsplat): a high-gradient primitive the world-size rule flags is split and
only children still over the limit go. Deleting it outright instead cost 1.9 dB of held-out PSNR after the first
opacity reset on a real phone capture (docs/real_captures.md), when every primitive's gradient is high.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, fields
from typing import Optional, Union

import torch

from warpgs.model.gaussians import GaussianModel, quat_to_rotmat
from warpgs.train import densify_stats
from warpgs.train.densify_stats import DensifyStats
from warpgs.train.optim import Optimizers, set_param_values, update_rows
from warpgs.train.schedule import DensifySchedule
from warpgs.train.screen_geometry import screen_grads_from_means_grad, screen_radii
from warpgs.train.unpool import midpoint_rows

WARN_PRUNED_FRACTION = 0.5  # a refine removing more than this share of the primitives warns


class PruningWarning(UserWarning):
    """A refine step removed most of the model (see DensifyStrategy.refine)."""


@dataclass
class StrategyConfig:
    grad_threshold: float = 2e-4  # mean NDC-gradient norm that marks a primitive for densification
    refine_start: int = 500  # densify/prune when refine_start < step < refine_stop and step % refine_every == 0
    refine_stop: int = 15_000
    refine_every: int = 100
    # The run's tail (train/schedule.py): with a known run length T, densification also stops at this fraction of
    # it (3DGS: 15k of 30k; the gaussians preset: 0.5), so the last (1 - fraction) x T steps train the model they
    # have. 1 (the default, for configs that set their own refine_stop): refine_stop alone.
    refine_stop_fraction: float = 1.0
    # opacities clamped to reset_opacity when step % reset_every == 0, while densifying (< the refine stop), and
    # with a whole interval of training after it before the run ends (when its length is known); 0 off
    reset_every: int = 3000
    reset_opacity: float = 0.01
    prune_opacity: float = 0.005  # prune below this opacity
    size_prune_start: int = 3000  # world/screen-size pruning only after this step (3DGS: after the first reset)
    prune_world_scale: float = 0.1  # prune if max scale > this x world_extent (see the module doc); 0 disables
    # Prune if the largest screen radius since the last refine exceeds this fraction of the image's larger side
    # (gsplat's prune_scale2d, 0.15 when enabled); 0 off, as in gsplat and, in effect, 3DGS.
    prune_screen_size: float = 0.0
    prune_screen_radius: float = 0.0  # the same in pixels whatever the resolution (older configs; warns); 0 off
    dense_scale: float = 0.01  # max scale <= this x extent -> clone, else split (3DGS's percent_dense)
    split_count: int = 2  # children per split primitive
    split_shrink: float = 1.6  # child scale = parent scale / split_shrink (3DGS: 0.8 x split_count)
    max_primitives: int = 1_000_000  # hard budget: never exceeded
    seed: int = 0  # for the split sampling
    # Proximity-guided unpooling (train/unpool.py, FSGS): at every unpool_every-th refine, a new primitive at the
    # midpoint of each link to one of a primitive's unpool_k nearest others longer than unpool_distance x the
    # scene extent (sparse views: gaps between the few points a start has); 0 off; "auto": by the number of
    # training views (unpool.RULE), which the trainer resolves before it builds the strategy
    unpool_every: Union[int, str] = 0
    unpool_k: int = 3
    unpool_distance: float = 0.05
    # AbsGS (gsplat's absgrad): the densification statistic sums each pixel's |dL/dmeans2d| per component instead of
    # the signed gradient, so a large Gaussian whose pixels pull it different ways still grows; its scale is larger,
    # so pair it with a larger grad_threshold (gsplat: 0.0008 against 0.0002). 3D Gaussians, one process or
    # data-parallel.
    absgrad: bool = False

    def __post_init__(self):
        if not isinstance(self.absgrad, bool):
            raise ValueError(f"absgrad: expected true or false, got {self.absgrad!r}")
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "absgrad" or (f.name == "unpool_every" and v == "auto"):
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{f.name}: expected a finite non-negative number, got {v!r}")
        for name in ("refine_every", "max_primitives", "unpool_k"):
            if int(getattr(self, name)) != getattr(self, name) or getattr(self, name) < 1:
                raise ValueError(f"{name}: expected a positive integer, got {getattr(self, name)}")
        if int(self.split_count) != self.split_count or self.split_count < 2:
            raise ValueError(f"split_count: expected an integer >= 2, got {self.split_count}")
        if self.split_shrink <= 0:
            raise ValueError(f"split_shrink: expected > 0, got {self.split_shrink}")
        if not 0 < self.refine_stop_fraction <= 1:
            raise ValueError(f"refine_stop_fraction: expected a fraction of the run in (0, 1], got "
                             f"{self.refine_stop_fraction}")
        if not 0 < self.reset_opacity < 1:
            raise ValueError(f"reset_opacity: expected a value in (0, 1), got {self.reset_opacity}")
        if self.prune_screen_size > 1:
            raise ValueError(f"prune_screen_size: a fraction of the image's larger side (e.g. 0.15), got "
                             f"{self.prune_screen_size}; a threshold in pixels is prune_screen_radius")


class DensifyStrategy:
    """Clone small / split large high-gradient primitives, prune faint and oversized ones, reset opacities,
    all under `max_primitives`. State (`state_dict`) is per-primitive statistics plus the RNG."""

    def __init__(self, config: Optional[StrategyConfig] = None, scene_extent: float = 1.0,
                 invisible_below: float = 0.0, world_extent: Optional[float] = None,
                 run_steps: Optional[int] = None):
        """scene_extent: 3DGS's camera extent, the unit of dense_scale (clone or split).
        run_steps: the run's length (the trainer's max_steps), which ends densification at refine_stop_fraction of
        it (None: refine_stop alone); `schedule.auto` (a train/schedule.py AutoStop, set by the trainer with
        steps=auto) may end it sooner, and its state is checkpointed with the strategy's.
        invisible_below: the renderer's alpha_min. Primitives with a lower opacity never reach a tile, so they
        get no gradient and would hold budget for good: they are pruned like those under prune_opacity.
        world_extent: the scene size the world-size rule measures against (default scene_extent); the trainer
        passes warpgs.data.extent.scene_content_extent, which stays valid when the cameras barely move."""
        self.config = config or StrategyConfig()
        if self.config.unpool_every == "auto":  # it depends on the run's views, which the strategy does not see
            raise ValueError('unpool_every: "auto" is resolved by the trainer (train/unpool.py unpool_every_for); '
                             'give a DensifyStrategy a number')
        self.invisible_below = float(invisible_below)
        for name, value in (("scene_extent", scene_extent), ("world_extent", world_extent)):
            if value is not None and not (math.isfinite(float(value)) and value > 0):
                raise ValueError(f"{name}: expected a finite positive number, got {value}")
        self.scene_extent = float(scene_extent)
        self.world_extent = float(scene_extent if world_extent is None else world_extent)
        if self.config.prune_screen_radius > 0:
            warnings.warn(f"strategy.prune_screen_radius={self.config.prune_screen_radius:g} px is not scale-aware "
                          f"(20 px is 13% of a 156 px image but 2% of a 960 px one); use prune_screen_size, a "
                          f"fraction of the image's larger side (gsplat: 0.15)", PruningWarning, stacklevel=2)
        self.generator = torch.Generator().manual_seed(int(self.config.seed))
        self.schedule = DensifySchedule(self.config, run_steps)  # when densification and resets happen
        self.stats: Optional[DensifyStats] = None  # set by initialize
        self.last_refine: Optional[dict] = None  # the latest refine's report (with "pruned_by")

    # ----- hooks -----
    def initialize(self, model: GaussianModel) -> None:
        n = model.num_primitives
        if n > self.config.max_primitives:
            raise ValueError(f"max_primitives: the model starts with {n} primitives, more than the budget "
                             f"{self.config.max_primitives} (initialise with max_points=...)")
        self.stats = DensifyStats(n, model.device)

    def step_pre_backward(self, model: GaussianModel, step: int) -> None:
        """Checks that the model was not resized behind the strategy's back. (Where a renderer exposes 2D
        means, this is where their .retain_grad() would go.)"""
        self._check_model(model)

    def step_post_backward(self, model: GaussianModel, optimizers: Optimizers, step: int, *,
                           visible: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                           grad2d: Optional[torch.Tensor] = None, near: float = 0.01) -> Optional[dict]:
        """Accumulate statistics, then refine / reset opacities on their steps. Returns a report dict on steps
        that changed the model ({"step", "cloned", "split", "pruned", "unpooled", "budget_dropped", "num_primitives",
        "opacity_reset"}), else None."""
        self._check_model(model)
        if not self.schedule.densifying(step):
            return None
        batched = viewmat.dim() == 3
        views = viewmat if batched else viewmat[None]
        Ks = K if batched else K[None]
        vis = visible if batched else visible[None]
        if grad2d is None:
            if views.shape[0] != 1:
                raise ValueError("grad2d: required for a batch of cameras (means.grad sums over them)")
            if model.means.grad is None:
                raise ValueError("grad2d: not given and model.means.grad is None; call step_post_backward after "
                                 "loss.backward() and before optimizer.zero_grad()")
            g2 = screen_grads_from_means_grad(model.means, model.means.grad, views[0], Ks[0], near)[None]
        else:
            g2 = grad2d if batched else grad2d[None]
        n = model.num_primitives
        if g2.shape != (views.shape[0], n, 2) or vis.shape != (views.shape[0], n):
            raise ValueError(f"grad2d/visible: expected [{n},2]/[{n}] per camera, got {list(g2.shape)}/{list(vis.shape)}")
        radii = None
        if self._screen_rules_on():
            radii = torch.stack([screen_radii(model, views[b], Ks[b], width, height, near) for b in range(len(views))])
        self.accumulate(g2, vis, radii, width, height)
        return self.maybe_refine(model, optimizers, step)

    def maybe_refine(self, model: GaussianModel, optimizers: Optimizers, step: int) -> Optional[dict]:
        """The end of step_post_backward, after the statistics are in: refine and/or reset opacities when this step
        is one of theirs. Returns the report (or None)."""
        cfg = self.config
        report = None
        if not self.schedule.densifying(step):
            return None
        if step > cfg.refine_start and step % cfg.refine_every == 0:
            report = self.refine(model, optimizers, step)
        if self.schedule.resets_at(step):
            self.reset_opacities(model, optimizers)
            report = report or {"step": step, "num_primitives": model.num_primitives}
            report["opacity_reset"] = True
        return report

    # ----- one camera at a time (batches of views with their own sizes, data-parallel training) -----
    def observe(self, model: GaussianModel, *, visible: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor,
                width: int, height: int, grad2d: Optional[torch.Tensor] = None,
                means_grad: Optional[torch.Tensor] = None, near: float = 0.01, views_in_loss: int = 1) -> dict:
        """One camera's statistics for this step, not yet added (add_observations adds them; merge_observations
        combines several cameras or ranks first). grad2d [N,2] is dL/dmeans2d of the loss this camera is part of;
        without it, means_grad [N,3] (this camera's share of dL/dmeans, default model.means.grad) is projected as
        step_post_backward does. views_in_loss: how many views the loss averages over (the global batch), the
        factor that turns the gradient of the mean back into this view's own gradient, as gsplat's n_cameras."""
        self._check_model(model)
        if grad2d is None:
            g = model.means.grad if means_grad is None else means_grad
            if g is None:
                raise ValueError("grad2d: not given and neither means_grad nor model.means.grad is set")
            grad2d = screen_grads_from_means_grad(model.means, g, viewmat, K, near)
        n = model.num_primitives
        if grad2d.shape != (n, 2) or visible.shape != (n,):
            raise ValueError(f"grad2d/visible: expected [{n},2]/[{n}], got {list(grad2d.shape)}/{list(visible.shape)}")
        radii = screen_radii(model, viewmat, K, width, height, near)[None] if self._screen_rules_on() else None
        return self.observations(grad2d[None], visible[None], radii, width, height, views_in_loss)

    observations = staticmethod(densify_stats.observations)  # grad2d, visible, radii, width, height -> dict
    merge_observations = staticmethod(densify_stats.merge_observations)

    def add_observations(self, obs: dict) -> None:
        """Add one step's observations (of one camera, merged cameras, or all ranks) to the statistics."""
        self._initialized().add(obs)

    # ----- pieces (usable on their own) -----
    @torch.no_grad()
    def accumulate(self, grad2d: torch.Tensor, visible: torch.Tensor, radii: Optional[torch.Tensor], width: int,
                   height: int) -> None:
        """grad2d [B,N,2] in pixels, visible [B,N] bool, radii [B,N] px: one training step's observations."""
        self.add_observations(self.observations(grad2d, visible, radii, width, height))

    @torch.no_grad()
    def refine(self, model: GaussianModel, optimizers: Optimizers, step: int) -> dict:
        """One densify-and-prune pass; resets the statistics. The report's "pruned_by" counts, per rule, the
        primitives that rule alone would remove (a primitive can fail several); more than half of the model
        pruned in one pass issues a PruningWarning with those counts."""
        cfg, extent = self.config, self.scene_extent
        self._check_model(model)
        n = model.num_primitives
        grads = self.stats.average_grads()
        max_scale = model.scales.amax(1)

        rules = self.prune_rules(model, step)
        pruned_by = {name: int(mask.sum()) for name, mask in rules.items()}
        # Grow, then prune, as 3DGS and gsplat: a primitive the world-size rule flags is still split when its
        # gradient asks for it, and its children (1/split_shrink the size) are tested again below; dropping it
        # outright leaves a hole that the next refines must regrow (issue 12, the phone capture). Copies of a
        # primitive that another rule flags would inherit what flagged it, so those are not densified.
        inherited = torch.zeros(n, dtype=torch.bool, device=max_scale.device)
        for name, mask in rules.items():
            if name != "world_size":
                inherited |= mask
        prune = inherited | rules["world_size"]
        cand = (grads >= cfg.grad_threshold) & ~inherited
        small = max_scale <= cfg.dense_scale * extent

        budget_dropped = 0
        base = n - int((prune & ~cand).sum())
        cost = torch.where(small, 1, cfg.split_count - 1)
        need = int(cost[cand].sum())
        room = cfg.max_primitives - base
        if need > room:
            # Keep the highest-gradient candidates whose total cost fits (stable sort: ties by index).
            idx = cand.nonzero().squeeze(1)
            order = idx[torch.argsort(grads[idx], descending=True, stable=True)]
            fits = torch.cumsum(cost[order], 0) <= max(room, 0)
            chosen = torch.zeros_like(cand)
            chosen[order[fits]] = True
            budget_dropped = int(cand.sum()) - int(chosen.sum())
            cand = chosen
        clone = cand & small
        split = cand & ~small
        # A flagged primitive that is neither split nor kept (budget) goes; a flagged clone goes with its copy.
        prune = prune & ~split
        clone = clone & ~prune

        new_rows = self._clone_rows(model, clone)
        split_rows = self._split_rows(model, split)
        children_pruned = 0
        if pruned_by["world_size"]:
            fits = ~self._too_big_for_world(torch.exp(split_rows["log_scales"]).amax(1))
            children_pruned = int((~fits).sum())
            split_rows = {name: rows[fits] for name, rows in split_rows.items()}
        append = {name: torch.cat([new_rows[name], split_rows[name]]) for name in model.params}
        update_rows(model, optimizers, keep=~prune & ~split, append=append)
        unpooled = self._unpool(model, optimizers, step)
        self.stats = DensifyStats(model.num_primitives, model.device)
        report = {"step": step, "cloned": int(clone.sum()), "split": int(split.sum()),
                  "pruned": int(prune.sum()) + children_pruned, "unpooled": unpooled,
                  "budget_dropped": budget_dropped, "num_primitives": model.num_primitives, "pruned_by": pruned_by}
        self.last_refine = report
        if report["pruned"] > WARN_PRUNED_FRACTION * n:
            warnings.warn(self._describe_pruning(report, n), PruningWarning, stacklevel=2)
        return report

    @torch.no_grad()
    def prune_rules(self, model: GaussianModel, step: int) -> dict:
        """{rule: [N] bool} of the primitives each pruning rule would remove at this step: "opacity" (below
        prune_opacity), "invisible" (below the renderer's alpha_min, not already under prune_opacity),
        "world_size" (largest scale over prune_world_scale x world_extent) and "screen_size" (largest screen
        radius since the last refine over prune_screen_size x the image's larger side, or prune_screen_radius
        px); the size rules only after size_prune_start."""
        cfg = self.config
        opacities = model.opacities
        none = torch.zeros_like(opacities, dtype=torch.bool)
        low = opacities < cfg.prune_opacity
        rules = {"opacity": low, "invisible": (opacities < self.invisible_below) & ~low,
                 "world_size": none, "screen_size": none}
        if step > cfg.size_prune_start:
            if cfg.prune_world_scale > 0:
                rules["world_size"] = self._too_big_for_world(model.scales.amax(1))
            screen = none
            if cfg.prune_screen_size > 0:
                screen = screen | (self.stats.max_screen > cfg.prune_screen_size)
            if cfg.prune_screen_radius > 0:
                screen = screen | (self.stats.max_radii > cfg.prune_screen_radius)
            rules["screen_size"] = screen
        return rules

    def _describe_pruning(self, report: dict, n: int) -> str:
        cfg, by = self.config, report["pruned_by"]
        screen = [f"> {cfg.prune_screen_size:g} x image size"] if cfg.prune_screen_size > 0 else []
        screen += [f"> {cfg.prune_screen_radius:g} px"] if cfg.prune_screen_radius > 0 else []
        return (f"strategy: the refine at step {report['step']} pruned {report['pruned']} of {n} primitives "
                f"({100.0 * report['pruned'] / max(n, 1):.0f}%); by rule (overlapping): "
                f"opacity < {cfg.prune_opacity:g}: {by['opacity']}, "
                f"invisible (opacity < alpha_min {self.invisible_below:.3g}): {by['invisible']}, "
                f"world size > {cfg.prune_world_scale:g} x extent {self.world_extent:.3g}: {by['world_size']}, "
                f"screen size {' or '.join(screen) or '(off)'}: {by['screen_size']}")

    @torch.no_grad()
    def reset_opacities(self, model: GaussianModel, optimizers: Optimizers) -> None:
        """opacity <- min(opacity, reset_opacity), done in logit space (monotone, no 0/1 round trip);
        the opacity moments are zeroed as in 3DGS."""
        cap = math.log(self.config.reset_opacity / (1.0 - self.config.reset_opacity))
        set_param_values(model, optimizers, "logit_opacities", model.logit_opacities.clamp_max(cap))

    # ----- checkpoints -----
    def state_dict(self) -> dict:
        state = {**self._initialized().tensors(), "generator": self.generator.get_state()}
        if self.schedule.auto is not None:  # plain Python values (the checkpoint moves only tensors)
            state["auto"] = self.schedule.auto.state_dict()
        return state

    def load_state_dict(self, state: dict) -> None:
        self.stats = DensifyStats.of(state)
        self.generator.set_state(state["generator"])
        if self.schedule.auto is not None and state.get("auto") is not None:
            self.schedule.auto.load_state_dict(state["auto"])

    # ----- internals -----
    def _too_big_for_world(self, max_scales: torch.Tensor) -> torch.Tensor:
        """The world-size rule on largest scales (prune_world_scale > 0 is the caller's check)."""
        return max_scales > self.config.prune_world_scale * self.world_extent

    def _screen_rules_on(self) -> bool:
        """Whether a screen-size rule reads the radii: only then are they computed and kept (the default has none,
        and projecting every covariance, then maxing and storing the result, is a dozen kernels over N a step)."""
        return self.config.prune_screen_size > 0 or self.config.prune_screen_radius > 0

    def _initialized(self) -> DensifyStats:
        if self.stats is None:
            raise ValueError("strategy: call initialize(model) first")
        return self.stats

    def _check_model(self, model: GaussianModel) -> None:
        tracked = len(self._initialized())
        if tracked != model.num_primitives:
            raise ValueError(f"model: has {model.num_primitives} primitives but the strategy tracks {tracked}; "
                             f"resize only through the strategy (or initialize again)")

    def _unpool(self, model: GaussianModel, optimizers: Optimizers, step: int) -> int:
        """Midpoint primitives in the gaps (train/unpool.py) at every unpool_every-th refine, within the budget;
        returns how many were added."""
        cfg = self.config
        if not cfg.unpool_every or (step // cfg.refine_every) % cfg.unpool_every:
            return 0
        room = cfg.max_primitives - model.num_primitives
        rows = midpoint_rows(model.params, cfg.unpool_k, cfg.unpool_distance * self.scene_extent, room)
        added = len(rows["means"])
        if added:
            keep = torch.ones(model.num_primitives, dtype=torch.bool, device=model.device)
            update_rows(model, optimizers, keep=keep, append=rows)
        return added

    @staticmethod
    def _clone_rows(model: GaussianModel, mask: torch.Tensor) -> dict:
        # Exact copies at the same place, as 3DGS's code: the next gradient steps pull them apart.
        return {name: p.detach()[mask] for name, p in model.params.items()}

    def _split_rows(self, model: GaussianModel, mask: torch.Tensor) -> dict:
        k = self.config.split_count
        rows = {name: p.detach()[mask].repeat_interleave(k, 0) for name, p in model.params.items()}
        scales = model.scales.detach()[mask].repeat_interleave(k, 0)
        # Children are sampled from the parent's own Gaussian (surfels: within their plane).
        std = torch.cat([scales, scales.new_zeros(len(scales), 3 - scales.shape[1])], 1)
        noise = torch.randn(std.shape, generator=self.generator).to(std.device) * std
        rot = quat_to_rotmat(rows["quats"])
        rows["means"] = rows["means"] + (rot @ noise[:, :, None])[:, :, 0]
        # In log space: exp() of a very negative log-scale (a flat axis) underflows to 0, and log(0) = -inf.
        rows["log_scales"] = rows["log_scales"] - math.log(self.config.split_shrink)
        return rows
