"""The trainer: data -> model -> render op -> losses -> optimizer step -> strategy, driven by a Config.

    from warpgs import Trainer, load_config
    result = Trainer(load_config("configs/default.yaml", ["steps=500"])).fit()
    result.metrics["psnr"], result.out_dir

One step: pick the next training view (a seeded random order, reshuffled every epoch), set the active SH degree
and the position learning rate, render exactly the outputs the active losses (and extensions) declare, sum the
weighted losses, backward, step Adam, let the densification strategy clone/split/prune under its hard budget.
With train.batch_size=B a step takes B views (loss = their mean); under torchrun the ranks share them out and sum
their gradients and statistics (train/distributed.py, docs/distributed.md).

Output folder: config.yaml (the resolved config), checkpoint.pt (atomic; model, optimizer, strategy, RNG
states, step), point_cloud.ply (3DGS layout; surfels in the 2DGS layout), renders/<split>/*.png,
metrics.json and log.jsonl (+ tensorboard/ with train.log=tensorboard). `Trainer(config, resume=True)`
continues from the checkpoint to the same result as an uninterrupted run (bit-exact on CPU). Ctrl-C stops at
the end of the current step and writes a checkpoint there (a second Ctrl-C aborts at once; the previous
checkpoint is then kept as it was). A non-finite loss, gradient or parameter stops training with
`NonFiniteError` naming the first offender; the last checkpoint is left as it was.

The Trainer composes collaborators that each own their state (docs/architecture.md has the table): LossSet
(train/loss_set.py), TrainViews (views.py), DensifyStrategy (strategy.py), Evaluator (evaluation.py),
NonFiniteGuard (guard.py), Checkpointer (state.py), TrainLog (log.py). It owns the model, what extensions add
(rendered feature names, modules and their optimizer), the optimizers, the background and the run counters.
"""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Callable, Dict, Iterable, List, Optional, Sequence, Union

import torch
from torch import nn

from warpgs.train import checkpoint as ckpt
from warpgs.config.loader import Config, load_config
from warpgs.train.phase_timer import PhaseTimer
from warpgs.train.stage_clock import StageClock
from warpgs.model.gaussians import GaussianModel
from warpgs.train.dropout import dropped_opacities, near_probabilities
from warpgs.train.extensions import Extension
from warpgs.model.rendering import check_outputs, focal_length, render_model, screen_filter
from warpgs.model import environment  # noqa: F401  (registers the built-in "environment" extension)
from warpgs.train import exposure  # noqa: F401  (registers the built-in "exposure" extension)
from warpgs.train import setup as train_setup
from warpgs.train import step as training_step
from warpgs.train import sharded_step
from warpgs.train.model_parallel import gather_model, gathered_training
from warpgs.train.batch import ViewPass
from warpgs.train.distributed import DistributedError
from warpgs.train.guard import NonFiniteError, NonFiniteGuard, StepGuard
from warpgs.train.log import TrainLog
from warpgs.train.loop import TrainingLoop, TrainResult
from warpgs.train.loss_set import LossSet, resolve_terms
from warpgs.train.state import Checkpointer, TrainingState
from warpgs.config.user_imports import import_user_module
from warpgs.train.trainer_build import TrainerBuild

VIEW_FIELDS = ("mask", "inv_depth_prior", "inv_depth_valid", "depth", "labels", "features")
__all__ = ["Trainer", "TrainResult", "NonFiniteError", "DistributedError", "train"]


class Trainer(TrainerBuild):
    """See the module docstring. `scene`/`model` override what the config would build; `extensions` are
    Extension objects (added to those the config names); `callbacks` are `fn(trainer, step, info)` called
    after every step."""

    def __init__(self, config: Union[None, str, Path, dict, Config] = None, *, overrides: Sequence[str] = (),
                 scene=None, model: Optional[GaussianModel] = None, extensions: Iterable[Extension] = (),
                 callbacks: Iterable[Callable] = (), resume: bool = False, out_dir=None, quiet: bool = False):
        self.config = load_config(config, overrides)  # a private, checked copy
        cfg = self.config
        for module in cfg.imports:  # e.g. modules that register custom losses or extensions
            import_user_module(module)
        self.clock = StageClock()  # the set-up's stages here, the final outputs' in fit (metrics.json)
        with self.clock.stage("join_ranks"):
            self._join_ranks(cfg, quiet)
        terms = resolve_terms(cfg.losses)

        if out_dir is not None:
            cfg.output.dir = str(out_dir)
        if cfg.output.dir is None:
            cfg.output.dir = str(Path("outputs") / train_setup.scene_label(cfg.data))
        self.out_dir = Path(cfg.output.dir)
        self.log = TrainLog(self.out_dir, kind=cfg.train.log if self.ranks.is_main else "none",
                            every=cfg.train.log_every)  # files open in fit()
        with self.clock.stage("load_scene"):  # with estimated depth priors
            self._load_scene(cfg, scene, terms)
        self.guard = NonFiniteGuard(self.named_parameters)
        self.step_guard = StepGuard(self.guard)  # the training step's use of it (deferred on a GPU)
        self.phases = PhaseTimer(self.device, cfg.train.profile_phases)
        self.checkpointer = Checkpointer(self.out_dir / cfg.output.checkpoint, self.device,
                                         guard=self.guard if cfg.train.nan_guard else None,
                                         write=self.ranks.is_main)

        state = self.checkpointer.load() if resume else None
        ckpt.seed_everything(cfg.train.seed)
        with self.clock.stage("build_model"):  # with its initial points (triangulated ones included)
            self._build_model(cfg, state, model)
        self._set_up_extensions(cfg, extensions, callbacks)
        self.loss_set = LossSet(terms, always=[o for e in self.extensions for o in e.outputs()])
        check_outputs(self.model.kind, self.outputs, "losses")
        if "features" in self.outputs and not self.feature_names and not self.extensions:
            raise ValueError("losses: a term needs the 'features' output but the model renders no features "
                             "(add model.features: {name: channels} or an extension)")
        self._build_optimizers(cfg)
        with self.clock.stage("load_views"):
            self._set_up_views_and_evaluation(cfg)
        with self.clock.stage("share_model"):
            self._resume_and_share_out(cfg, state)

    # ----- the run's position (RunCounters) and its collaborators' views of it --------------------------------
    @property
    def step(self) -> int:
        return self.counters.step

    @step.setter
    def step(self, value: int) -> None:
        self.counters.step = int(value)

    @property
    def train_seconds(self) -> float:
        return self.counters.train_seconds

    @property
    def last_loss(self) -> Optional[float]:
        return self.counters.loss()

    @property
    def at_boundary(self) -> bool:
        """False while a step is running (a checkpoint then would hold half a step)."""
        return self._at_boundary

    @property
    def num_primitives(self) -> int:
        """The model's primitives over all ranks (with train.parallel=model self.model is this rank's share)."""
        return self._total_primitives if self.model_parallel else self.model.num_primitives

    def count_primitives(self) -> int:
        """Recount num_primitives after the shards changed (a collective with train.parallel=model)."""
        if self.model_parallel:
            counts = self.ranks.all_gather_object(self.model.num_primitives, what="counting the primitives")
            self._total_primitives = int(sum(counts))
        return self.num_primitives

    @contextlib.contextmanager
    def whole_model(self, with_state: bool = False, device="cpu"):
        """With train.parallel=model: the whole model (and with_state: its optimizer and strategy) gathered from
        every rank's share onto `device` and in place of the shard until the block ends, for PLY files and
        checkpoints in the single-process format. A collective: every rank enters it. Otherwise a no-op."""
        if not self.model_parallel:
            yield self.model
            return
        shard, optimizer, strategy = self.model, self.optimizer, self.strategy
        if with_state:
            whole, self.optimizer, self.strategy = gathered_training(
                shard, optimizer, strategy, self.ranks, budget=self.config.strategy.max_primitives, device=device)
        else:
            whole = gather_model(shard, self.ranks, device)
        whole.active_sh_degree = shard.active_sh_degree
        self.model = whole
        try:
            yield whole
        finally:
            self.model, self.optimizer, self.strategy = shard, optimizer, strategy

    @property
    def history(self) -> List[dict]:
        return self.evaluator.history

    @property
    def terms(self) -> list:
        return self.loss_set.terms

    @property
    def outputs(self) -> tuple:
        """The outputs rendered over the whole run (the active terms' and the extensions')."""
        return self.loss_set.outputs

    @property
    def checkpoint_path(self) -> Path:
        return self.checkpointer.path

    @property
    def train_indices(self) -> List[int]:
        return self.views.indices

    # ----- extension API --------------------------------------------------------------------------------------
    def add_extra(self, name: str, values: torch.Tensor, *, lr: Optional[float] = None, render: bool = True) -> None:
        """A learnable per-primitive parameter [N, C] (copied/pruned with the primitives, saved in the PLY).
        render=True concatenates it into the `features` input when a loss asks for that output."""
        if name in self.model.params:  # restored from a checkpoint
            if self.model.params[name].shape[1:] != torch.Size(values.shape[1:]):
                raise ValueError(f"add_extra: {name!r} exists with shape {list(self.model.params[name].shape)}")
        else:
            self.model.add_extra(name, values)
        if lr is not None:
            self.config.optim.extras_lr[name] = float(lr)
        if render and name not in self.feature_names:
            self.feature_names.append(name)

    def add_module(self, name: str, module: nn.Module, *, lr: float) -> None:
        """An nn.Module trained alongside (its own Adam group; saved in checkpoints; in batch["modules"])."""
        if name in self.modules:
            raise ValueError(f"add_module: a module {name!r} already exists")
        self.modules[name] = module.to(self.device)
        self._module_lrs[name] = float(lr)

    @property
    def optimizers(self) -> list:
        return [self.optimizer] + ([self.module_optimizer] if self.module_optimizer is not None else [])

    @property
    def feature_slices(self) -> Dict[str, slice]:
        out, start = {}, 0
        for name in self.feature_names:
            c = self.model.params[name].shape[1]
            out[name] = slice(start, start + c)
            start += c
        return out

    def learning_rates(self) -> Dict[str, float]:
        """{param group or module name: its current learning rate}."""
        return {g.get("name", str(i)): g["lr"] for opt in self.optimizers for i, g in enumerate(opt.param_groups)}

    def named_parameters(self):
        """(name, tensor) of every trained parameter: the model's, then the modules' as modules.<name>."""
        for name, p in self.model.params.items():
            yield name, p
        for name, p in self.modules.named_parameters():
            yield f"modules.{name}", p

    def check_finite(self, step: int, result=None) -> None:
        self.guard.check(step, result)

    # ----- one step -------------------------------------------------------------------------------------------
    def view(self, index: int):
        """Training view `index` as this step trains on it (train.resolution_schedule's scale)."""
        return self.scaled_views.at(self.views.view(index), self.step)

    def make_batch(self, view, step: int) -> dict:
        """What losses read: image, camera, the view's optional maps (mask, inv_depth_prior + inv_depth_valid,
        depth, labels, features) when the scene has them, and the trainer's modules and feature slices."""
        batch = {"image": view.image, "view": view, "name": view.name, "index": view.index,
                 "viewmat": view.viewmat, "K": view.K, "width": view.width, "height": view.height,
                 "background": self.background, "step": step, "max_steps": self.max_steps,
                 "modules": self.modules, "feature_slices": self.feature_slices}
        for key in VIEW_FIELDS:
            value = getattr(view, key, None)
            if value is not None:
                batch[key] = value
        for ext in self.extensions:
            batch = ext.make_batch(self, view, batch)
        return batch

    def render_inputs(self, batch: dict, step: int, outputs: Sequence[str]) -> dict:
        inputs = self.model.render_inputs()
        if "features" in outputs and self.feature_names:
            inputs["features"] = torch.cat([self.model.params[n] for n in self.feature_names], 1)
        for ext in self.extensions:
            inputs = ext.render_inputs(self, inputs, batch, step)
        return inputs

    def render(self, view, outputs: Sequence[str] = ("rgb",), batch: Optional[dict] = None, *,
               track_means2d: bool = False, step: Optional[int] = None, speculative_pairs: bool = False,
               drop_rate: float = 0.0):
        """Renders the model (with the extensions' inputs and outputs) from `view`. drop_rate: leave out that random
        share of the primitives, the others' opacities compensated (train.drop_rate; training views only)."""
        step = self.step if step is None else step
        batch = self.make_batch(view, step) if batch is None else batch
        t = self.config.train
        extra = [o for e in self.extensions for o in e.outputs() if o not in outputs]
        outputs = tuple(outputs) + tuple(dict.fromkeys(extra))
        # The screen-space filter scaled with the image (model/rendering.py): a scene view's focal length from its
        # camera on the host (no device read), another camera's from its K.
        index, cams = getattr(view, "index", -1), self.scene.cameras
        same = 0 <= index < len(cams) and (cams[index].width, cams[index].height) == (view.width, view.height)
        filters = screen_filter(self.model.kind, focal_length(cams[index].K if same else view.K), self.training_focal,
                                t.surfel_screen_sigma)
        inputs = self.render_inputs(batch, step, outputs)
        if drop_rate:
            near = (near_probabilities(inputs["means"], view.viewmat, drop_rate, t.drop_near) if t.drop_near
                    else None)
            inputs["opacities"] = dropped_opacities(inputs["opacities"], drop_rate, near)
        out = render_model(self.model, view.viewmat, view.K, view.width, view.height, outputs=outputs,
                           background=self.background, inputs=inputs,
                           track_means2d=track_means2d, absgrad=self.config.strategy.absgrad,
                           check_inputs=not t.nan_guard,
                           deterministic=t.deterministic or None, speculative_pairs=speculative_pairs, **filters,
                           **t.render_options())
        overflowed = out.pairs_overflowed  # an extension's own RenderOutput must not lose it (the step's skip)
        for ext in self.extensions:
            out = ext.after_render(self, out, batch, step)
        if overflowed is not None and getattr(out, "pairs_overflowed", None) is None:
            out.pairs_overflowed = overflowed
        return out

    def outputs_at(self, step: int) -> tuple:
        """The outputs rendered at this step: those of the terms whose scheduled weight is not 0 now, plus the
        extensions' (self.outputs is the union over the whole run)."""
        return self.loss_set.outputs_at(step, self.max_steps)

    def train_step(self) -> dict:
        """One optimisation step at self.step over train.batch_size views (train/step.py has how)."""
        self._at_boundary = False
        info = (sharded_step.train_step_sharded if self.model_parallel else training_step.train_step)(self)
        self._at_boundary = True
        return info

    def view_pass(self, view, step: int, *, views_in_loss: int = 1, densify: bool = False,
                  first: bool = True) -> ViewPass:
        """Render one view of the step, score it and back-propagate its share (train/step.py)."""
        return training_step.view_pass(self, view, step, views_in_loss=views_in_loss, densify=densify, first=first)

    def base_learning_rates(self) -> Dict[str, float]:
        """{param group: its configured lr} before any batch scaling (the means' is set every step anyway)."""
        base = {name: self.config.optim.lr_for(name, self.extent) for name in self.model.params}
        base.update(self._module_lrs)
        return base

    # ----- evaluation and checkpoints (Evaluator, Checkpointer) -----------------------------------------------
    def eval_views(self, split: Optional[str] = None) -> tuple:
        """(split actually used, views): the test views, or the training views when there are none."""
        return self.evaluator.eval_views(split)

    def lpips(self):
        return self.evaluator.lpips()

    def evaluate(self, *, save_images: bool = False, max_views: int = 0) -> dict:
        return self.evaluator.evaluate(save_images=save_images, max_views=max_views)

    @torch.no_grad()
    def _render_round(self, cameras) -> torch.Tensor:
        """train.parallel=model: this rank's camera of an evaluation round (one view per rank), from every shard."""
        view = cameras[self.ranks.rank]
        out = sharded_step.render_round(self, cameras, ("rgb",), self.make_batch(view, self.step), self.step)
        return out.rgb

    def training_state(self) -> TrainingState:
        """The parts a checkpoint holds, as they are now."""
        return TrainingState(self.counters, self.model, self.optimizer, self.module_optimizer, self.modules,
                             self.strategy, self.extensions, self.views, self.evaluator, self.config,
                             best=None if self.model_parallel else self.best_state)

    def state_dict(self) -> dict:
        return self.checkpointer.state_dict(self.training_state())

    def save_checkpoint(self) -> Path:
        """Write checkpoint.pt (rank 0 only; the other ranks wait for it at a barrier). train.parallel=model:
        each rank writes its share and checkpoint.pt is their index (output.checkpoint_shards=false: one file of
        the whole model gathered)."""
        if not self._at_boundary:
            raise RuntimeError("save_checkpoint: only between steps")
        self.step_guard.settle()  # the last step's deferred NaN check, before anything is written
        if self.model_parallel and self.config.output.checkpoint_shards:  # each rank its share; no gather
            path = self.checkpointer.save_sharded(self.training_state(), self.ranks)
        else:
            with self.whole_model(with_state=True):
                path = self.checkpointer.save(self.training_state())
        self.ranks.barrier(f"waiting for rank 0 to write the checkpoint of step {self.step}")
        return path

    # ----- the loop (TrainingLoop in loop.py) -----------------------------------------------------------------
    def fit(self) -> TrainResult:
        """Train from self.step to max_steps, then write the final outputs (see the module docstring)."""
        if self.config.train.viewer and self.viewer is None and self.ranks.is_main:  # serves until the process ends
            from warpgs.viewer.live import start_live_viewer
            self.viewer = start_live_viewer(self, self.config.train.viewer_port)
        threads = self.config.train.threads or (1 if self.device.type == "cpu" else 0)
        previous = torch.get_num_threads()
        if threads:
            # On CPU the Warp kernels spread over their own thread pool; torch's OpenMP workers spinning next to
            # them (and next to any other process) cost far more than they save on these small per-image ops:
            # measured on the 2-core machine with another job running, 0.06-0.15 s a step with 1 thread against
            # 0.7 s with 2 (128x96, 3k Gaussians).
            torch.set_num_threads(threads)
        try:
            with self.log.open(self.step):
                return TrainingLoop(self).run()
        finally:
            torch.set_num_threads(previous)

    def finish(self) -> TrainResult:
        """Final checkpoint, PLY, test renders and metrics.json."""
        return TrainingLoop(self).finish()

    def close(self) -> None:
        """Leave the process group if this Trainer joined it (warpgs-train does this after fit())."""
        self.ranks.close()


def train(config=None, overrides: Sequence[str] = (), **kwargs) -> TrainResult:
    """Shorthand: Trainer(config, overrides=overrides, **kwargs).fit()."""
    return Trainer(config, overrides=overrides, **kwargs).fit()
