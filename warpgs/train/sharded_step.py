"""One optimisation step of the Trainer with train.parallel=model: each rank owns a share of the primitives
(train/model_parallel.py) and the step's views are rendered in rounds of one view per rank, each from every
rank's primitives (render/sharded.py). Each rank's loss back-propagates through the splat exchange into every
owner's rows, so parameter gradients need no all-reduce (the extensions' modules, held whole on every rank, still
are); densification statistics are per owner: each rank observes its own rows in every camera of the round.

The loss is the mean over the batch's views, as in data-parallel training, so the same global batch gives the
same gradients (tests/test_model_parallel_train.py)."""
from __future__ import annotations

import time

import torch

from warpgs.train.batch import (HostScalars, ViewPass, batch_result, batch_summary, local_sums, scalar_names,
                                 without_graph)
from warpgs.train.guard import NonFiniteError
from warpgs.train.model_parallel import render_shard, require_gaussians
from warpgs.train.opacity_decay import decay_opacities
from warpgs.train.step import end_step, set_step_schedule


def check_config(cfg, world_size: int) -> None:
    """What train.parallel=model needs of a config, checked before anything is built: 3D Gaussians, rounds of one
    view per rank that the batch fills, no footprint truncation (the splat exchange's culling does not take it), no
    live viewer (each process holds only a share of the primitives)."""
    require_gaussians(cfg.model.kind)
    train = cfg.train
    if train.batch_size % world_size:
        raise ValueError(f"train.batch_size: {train.batch_size} is not a multiple of the {world_size} processes; "
                         f"with train.parallel=model every rank renders one view of each round (e.g. "
                         f"train.batch_size={world_size})")
    if train.max_sigmas:
        raise ValueError("train.max_sigmas: footprint truncation is not supported with train.parallel=model")
    if train.viewer:
        raise ValueError("train.viewer: not available with train.parallel=model (each process holds only a share "
                         "of the primitives); view the output folder afterwards with warpgs-view")


def train_step_sharded(trainer) -> dict:
    """train_step (train/step.py) for a model sharded over the ranks; returns the same info."""
    cfg, model, step, ranks = trainer.config, trainer.model, trainer.step, trainer.ranks
    t0 = time.perf_counter()
    phases = trainer.phases  # train.profile_phases
    phases.start()
    drawn = trainer.views.draw(trainer.batch_size)  # the global batch, drawn alike on every rank
    world = ranks.world_size
    densify = set_step_schedule(trainer, step)  # as the single-process step (train.steps=auto's anneal included)
    phases.mark("draw_views")
    passes, seen = [], []
    for start in range(0, len(drawn), world):
        cameras = [trainer.view(i) for i in drawn[start:start + world]]
        p, round_seen = view_pass_sharded(trainer, cameras, step, views_in_loss=len(drawn), densify=densify,
                                          first=not passes)
        passes.append(p)
        seen += round_seen
    phases.mark("render_backward")  # the all-to-all exchanges of the rounds included
    names = scalar_names(passes)
    # Only the modules' gradients are summed over the ranks (the primitives' arrived through the exchange); the
    # non-finite flag rides along, so a NaN on one rank stops every rank at the same step.
    finite = not cfg.train.nan_guard or all(bool(torch.isfinite(p.grad).all())
                                            for _, p in trainer.named_parameters() if p.grad is not None)
    sums = ranks.all_reduce_gradients([p for _, p in trainer.modules.named_parameters()],
                                      local_sums(passes, names) + [float(trainer.stop_requested), float(not finite)],
                                      step)
    nonfinite_elsewhere, stop = sums.pop() > 0, sums.pop() > 0
    phases.mark("all_reduce")
    summary = batch_summary(sums, names, len(drawn))
    result = batch_result(summary, passes[0].result)
    if cfg.train.nan_guard:  # before the optimizer step, so nothing non-finite is ever applied
        trainer.check_finite(step, result)
        if nonfinite_elsewhere:
            raise NonFiniteError(step, "another rank", "another rank's gradients are not finite (that rank's error "
                                                       "names the first offender)")
    for opt in trainer.optimizers:
        opt.step()
    decay_opacities(model, cfg.train.opacity_decay)  # per row: each rank its own
    phases.mark("optimizer")
    report = None
    if densify:  # each owner its own rows in every camera, after the optimizer step as in train/step.py
        observed = (trainer.strategy.observe(model, visible=binned, viewmat=cam.viewmat, K=cam.K, width=cam.width,
                                             height=cam.height, grad2d=grad2d, near=cfg.train.near,
                                             views_in_loss=len(drawn))
                    for cam, binned, grad2d in seen)
        trainer.strategy.add_observations(trainer.strategy.merge_observations(observed))
        report = trainer.strategy.maybe_refine(model, trainer.optimizer, step)
        if report is not None:  # refine steps are the same on every rank
            trainer.count_primitives()
        phases.mark("densify")
    return end_step(trainer, step, t0, summary, report, passes, drawn, stop)


def view_pass_sharded(trainer, cameras, step: int, *, views_in_loss: int, densify: bool, first: bool):
    """One round: this rank's camera (cameras[rank]) rendered from every shard, scored, back-propagated (its share
    loss / views_in_loss). Returns (ViewPass of this rank's view, [(camera, [N] bool: this rank's rows that
    its blend binned, [N,2] their dL/dmeans2d)] for every camera of the round when densifying, else [])."""
    model, ranks = trainer.model, trainer.ranks
    view = cameras[ranks.rank]
    batch = trainer.make_batch(view, step)
    out = render_round(trainer, cameras, trainer.outputs_at(step), batch, step, track_means2d=densify)
    result = trainer.loss_set(out, batch, model, step, trainer.max_steps)
    if first:
        trainer.strategy.step_pre_backward(model, step)
    (result.total / views_in_loss).backward()
    result = without_graph(result)
    p = ViewPass(view=view, result=result, scalars=HostScalars(result, out.rgb, view.image))
    if not densify:
        return p, []
    grads = out.means2d.grad if out.means2d.grad is not None else torch.zeros_like(out.means2d)
    return p, [(cam, out.seen[j], grads[j]) for j, cam in enumerate(cameras)]


def render_round(trainer, cameras, outputs, batch: dict, step: int, *, track_means2d: bool = False):
    """This rank's camera of the round (cameras: one view per rank, the same list on every rank) rendered from every
    shard, with the outputs the extensions add and their after_render, as Trainer.render does for one view. A
    collective: every rank calls it with the same cameras."""
    cfg = trainer.config
    extra = [o for e in trainer.extensions for o in e.outputs() if o not in outputs]
    outputs = tuple(outputs) + tuple(dict.fromkeys(extra))
    options = cfg.train.render_options()
    options.pop("max_sigmas")  # 0: check_config
    out = render_shard(trainer.model, torch.stack([c.viewmat for c in cameras]), torch.stack([c.K for c in cameras]),
                       [c.width for c in cameras], [c.height for c in cameras], outputs=outputs,
                       background=trainer.background, inputs=trainer.render_inputs(batch, step, outputs),
                       track_means2d=track_means2d, **options)
    for ext in trainer.extensions:
        out = ext.after_render(trainer, out, batch, step)
    return out
