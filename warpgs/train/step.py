"""One optimisation step of the Trainer: draw the step's views, render and score each (view_pass), reduce over the
ranks, step the optimizers, let the strategy densify. Functions of the trainer, whose Trainer.train_step and
Trainer.view_pass are the public spelling."""
from __future__ import annotations

import time

from warpgs.train import setup as train_setup
from warpgs.train.batch import (BatchScalars, HostScalars, ViewPass, batch_result, batch_summary,
                                device_batch_result, local_sums, scalar_names, without_graph)
from warpgs.train.dropout import rate_at
from warpgs.train.opacity_decay import decay_opacities
from warpgs.train.optim import means_lr_at, update_learning_rates
from warpgs.train.step_info import StepInfo
from warpgs.train.virtual_views import virtual_loss


def train_step(trainer) -> dict:
    """One optimisation step at trainer.step over train.batch_size views (this rank's share of them when
    distributed); returns info for logging and hooks. The loss is the mean over the batch's views; each view is
    rendered, scored and back-propagated in turn (ViewPass, train/batch.py), gradients and densification
    statistics are summed over the ranks, then every rank takes the same optimizer and strategy step. With one
    view on one process this is the single-view step exactly (tests/test_train_batch.py checks bit for bit)."""
    cfg, model, step = trainer.config, trainer.model, trainer.step
    t0 = time.perf_counter()
    phases = trainer.phases  # train.profile_phases (off: every call returns at once)
    phases.start()
    drawn = trainer.views.draw(trainer.batch_size)  # the global batch, drawn alike on every rank
    mine = [trainer.view(i) for i in drawn[trainer.ranks.shard(len(drawn))]]
    densify = set_step_schedule(trainer, step)
    phases.mark("draw_views")
    passes = []
    for view in mine:
        # Through the method, so a Trainer subclass that overrides view_pass is honoured.
        passes.append(trainer.view_pass(view, step, views_in_loss=len(drawn), densify=densify, first=not passes))
    if trainer.virtual_views is not None and step % trainer.virtual_every == 0:
        virtual_pass(trainer, step)
    phases.mark("render_backward")
    names = scalar_names(passes)
    stop = False
    if trainer.ranks.enabled:
        # A Ctrl-C on any rank rides along with the sums, so all ranks learn of it at the same step.
        sums = trainer.ranks.all_reduce_gradients([p for _, p in trainer.named_parameters()],
                                                  local_sums(passes, names) + [float(trainer.stop_requested)], step)
        stop = sums.pop() > 0
    phases.mark("all_reduce")
    # The loss the guard checks, and what the step's info reads its loss values from when they are first used
    # (train/step_info.py): the loop does so a step later, so a GPU step ends without waiting for its own backward.
    if len(drawn) == 1:
        result, summary = passes[0].result, passes[0].scalars  # not the ViewPass: its buffers die with the step
    elif trainer.ranks.enabled:
        summary = batch_summary(sums, names, len(drawn))
        result = batch_result(summary, passes[0].result)
    else:  # the batch's means on the device: no host read before the optimizer
        result, summary = device_batch_result(passes, len(drawn)), BatchScalars(passes, names, len(drawn))
    if cfg.train.nan_guard:  # before the optimizer step, so nothing non-finite is ever applied (train/guard.py)
        trainer.step_guard.before_optimizers(step, result, trainer.optimizers, defer=not trainer.ranks.enabled,
                                             dropped=[p.pairs_overflowed for p in passes
                                                      if p.pairs_overflowed is not None])
    for opt in trainer.optimizers:
        opt.step()
    trainer.step_guard.after_optimizers(trainer.optimizers)
    decay_opacities(model, cfg.train.opacity_decay)
    phases.mark("optimizer")
    report = None
    if densify:  # after the optimizer step, as 3DGS: the screen radii are those of the updated model
        observed = trainer.strategy.merge_observations(
            trainer.strategy.observe(model, visible=p.visible, viewmat=p.view.viewmat, K=p.view.K,
                                  width=p.view.width, height=p.view.height, grad2d=p.grad2d,
                                  means_grad=p.means_grad, near=cfg.train.near, views_in_loss=len(drawn))
            for p in passes)
        trainer.strategy.add_observations(trainer.ranks.all_reduce_observations(observed, step))
        report = trainer.strategy.maybe_refine(model, trainer.optimizer, step)
        if report is not None and trainer.ranks.enabled:
            trainer.ranks.check_same(model.num_primitives, f"the number of primitives after step {step}")
        phases.mark("densify")
    return end_step(trainer, step, t0, summary, report, passes, drawn, stop)


def set_step_schedule(trainer, step: int) -> bool:
    """The step's SH degree and learning rates (train.steps=auto anneals the position rate once densification
    stops); returns whether the step densifies (the schedule's stop, not refine_stop alone). Both steps use it."""
    cfg, model = trainer.config, trainer.model
    model.active_sh_degree = train_setup.active_sh_degree(step, cfg, model.max_sh_degree)
    schedule = trainer.strategy.schedule  # train/schedule.py
    annealed = None
    if schedule.auto is not None:
        annealed = schedule.auto.means_lr(
            step, lambda s: means_lr_at(s, cfg.optim, trainer.extent, trainer.max_steps))
    update_learning_rates(trainer.optimizer, step, cfg.optim, trainer.extent, trainer.max_steps, trainer.lr_scale,
                          means_lr=annealed)
    return schedule.densifying(step)


def end_step(trainer, step: int, t0: float, summary, report, passes, drawn, stop: bool) -> StepInfo:
    """Clear the gradients, advance the run's counters, and return the step's info (train_step's result). summary:
    {"loss", "values", "psnr"}, or what reads them (a view's HostScalars or a BatchScalars) when the info's loss
    values are first used."""
    for opt in trainer.optimizers:
        opt.zero_grad(set_to_none=True)
    trainer.model.zero_grad(set_to_none=True)
    trainer.phases.mark("zero_grad")
    trainer.phases.end_step()
    trainer.counters.train_seconds += time.perf_counter() - t0
    trainer.counters.step = step + 1
    items = {"step": step, "num_primitives": trainer.num_primitives, "densify": report,
             "view": passes[0].view.name, "views": [trainer.scene.cameras[i].name for i in drawn], "stop": stop}
    info = (StepInfo(items, summary.summary, ready=summary.ready) if hasattr(summary, "summary")
            else StepInfo({**items, **summary}))
    trainer.counters.last_info = info  # its loss is read when asked for (RunCounters.loss)
    return info


def view_pass(trainer, view, step: int, *, views_in_loss: int = 1, densify: bool = False,
              first: bool = True) -> ViewPass:
    """Render one view of the step, score it, and back-propagate its share (loss / views_in_loss) into the
    parameters' .grad; returns what the rest of the step needs from it. `first`: the step's first view (the
    strategy checks the model before the first backward)."""
    model = trainer.model
    batch = trainer.make_batch(view, step)
    out = trainer.render(view, trainer.outputs_at(step), batch, track_means2d=densify, step=step,
                         speculative_pairs=speculative_pairs(trainer),
                         drop_rate=rate_at(trainer.drop_rate, trainer.config.train.drop_schedule, step,
                                           trainer.max_steps))
    result = trainer.loss_set(out, batch, model, step, trainer.max_steps)
    if first:
        trainer.strategy.step_pre_backward(model, step)
    # Surfels give no means2d: this view's share of means.grad is what the strategy projects instead (with a
    # single view, means.grad itself, read after the step as before).
    own_means_grad = densify and out.means2d is None and views_in_loss > 1
    before = model.means.grad.clone() if own_means_grad and model.means.grad is not None else None
    (result.total if views_in_loss == 1 else result.total / views_in_loss).backward()
    result = without_graph(result)
    # The scalars for the log and the progress line: one device-to-host copy, read when the info is (a step later).
    p = ViewPass(view=view, result=result, scalars=HostScalars(result, out.rgb, view.image),
                 pairs_overflowed=out.pairs_overflowed)
    if densify:
        p.visible = out.visible
        p.grad2d = None
        if out.means2d is not None:  # strategy.absgrad: the summed |dL/dmeans2d| (rasterize's absgrad) instead
            p.grad2d = out.means2d.absgrad if trainer.config.strategy.absgrad else out.means2d.grad
        if own_means_grad:
            g = model.means.grad
            p.means_grad = g.clone() if before is None else g - before
    return p


def virtual_pass(trainer, step: int) -> None:
    """Render the step's virtual view (train.virtual_views) and back-propagate its loss into the parameters'
    .grad beside the training views'; every rank renders the same one, so each adds its share."""
    t = trainer.config.train
    view = trainer.virtual_views.draw(step)
    out = trainer.render(view, ("rgb", "inv_depth"), trainer.make_batch(view, step), step=step)
    (virtual_loss(out, view, t.virtual_rgb, t.virtual_depth) / trainer.ranks.world_size).backward()


def speculative_pairs(trainer) -> bool:
    """Whether the step's renders may size their tile pairs from earlier renders (train.speculative_pairs): only
    where a render that did not fit can be skipped on the device, i.e. where the NaN guard defers (fused Adam on one
    process, train/guard.py), on a GPU, and not in deterministic runs."""
    t = trainer.config.train
    return (t.speculative_pairs and t.nan_guard and not t.deterministic and trainer.device.type == "cuda"
            and not trainer.ranks.enabled
            and trainer.step_guard.can_defer(trainer.optimizers))
