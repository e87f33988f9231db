"""The Trainer's construction, in the order __init__ calls it: ranks and device, the scene, the model, extensions,
optimizers and strategy, training views and evaluation, then a checkpoint's state and the model's share per rank.
A base class of Trainer (train/trainer.py) so that the trainer's file keeps what a run does step by step."""
from __future__ import annotations

import threading
from dataclasses import replace
from typing import Callable, Dict, Iterable, List, Optional

import torch
from torch import nn

from warpgs.config.loader import Config
from warpgs.data.extent import scene_content_extent
from warpgs.model.gaussians import GaussianModel
from warpgs.train import checkpoint as ckpt
from warpgs.train import setup as train_setup
from warpgs.train import sharded_step
from warpgs.train.best_state import BestState
from warpgs.train.determinism import use_deterministic_algorithms
from warpgs.train.distributed import setup_ranks, sync_model
from warpgs.train.dropout import drop_rate_for
from warpgs.train.evaluation import Evaluator
from warpgs.train.extensions import CallbackExtension, Extension, build_extension
from warpgs.train.lifted_prior import confidence_for
from warpgs.train.model_parallel import move_training, shard_training
from warpgs.train.optim import build_optimizer, fused_adam
from warpgs.train.resolution import ScaledViews
from warpgs.train.scaling import apply_batch_scaling, lr_scale
from warpgs.train.schedule import AutoStop, validation_split
from warpgs.train.state import RunCounters
from warpgs.train.steps_by_views import fixed_steps
from warpgs.train.strategy import DensifyStrategy
from warpgs.train.unpool import unpool_every_for
from warpgs.train.views import TrainViews
from warpgs.train.virtual_views import virtual_every, virtual_views_for


class TrainerBuild:
    """What Trainer.__init__ calls, one stage a method; each sets the attributes its docstring names."""

    # ----- construction, in order (__init__) ---------------------------------------------------------------------
    def _model_device(self) -> torch.device:
        """Where the whole model is built or loaded: train.parallel=model builds it in CPU memory, and each rank's
        GPU then gets its share (_resume_and_share_out)."""
        return torch.device("cpu") if self.model_parallel else self.device

    def _join_ranks(self, cfg: Config, quiet: bool) -> None:
        """Ranks and device (train/distributed.py), the console voice, the batch and parallel mode."""
        # Under torchrun (WORLD_SIZE > 1) this joins the process group; on one process `ranks` is a no-op.
        self.ranks, self.device = setup_ranks(train_setup.resolve_device(cfg.train.device),
                                              backend=cfg.train.dist_backend, timeout=cfg.train.dist_timeout)
        self.quiet = quiet or not self.ranks.is_main  # one console voice: rank 0's
        self.batch_size = cfg.train.batch_size
        if self.batch_size < self.ranks.world_size:
            raise ValueError(f"train.batch_size: {self.batch_size} is less than the {self.ranks.world_size} "
                             f"processes; it counts the views of a step over all of them (each renders its "
                             f"share), e.g. train.batch_size={self.ranks.world_size}")
        # train.parallel=model: each rank owns a share of the primitives (train/sharded_step.py); on one process
        # there is nothing to share and the run is the usual one.
        self.model_parallel = cfg.train.parallel == "model" and self.ranks.enabled
        if self.model_parallel:
            sharded_step.check_config(cfg, self.ranks.world_size)
        if cfg.train.deterministic:
            use_deterministic_algorithms(self.device, self.model_parallel)
        train_setup.install_training_ssim(cfg.train.fused_ssim, self.device)

    def _load_scene(self, cfg: Config, scene, terms) -> None:
        """The scene (given, or loaded by rank 0 first), its extents, focal length, background and step bound."""
        def readers(num_train_views: int) -> str:
            return train_setup.what_reads_priors(cfg, terms, num_train_views)

        # Rank 0 first: loading can write caches (the built-in scene, estimated depth priors) the others then read.
        self.scene = scene if scene is not None else self.ranks.rank0_first(
            lambda: train_setup.load_training_scene(cfg.data, self.out_dir, readers), "loading the scene")
        self.extent = train_setup.scene_extent(self.scene, cfg.train.scene_extent)
        # The training images' focal length: renders scale the screen-space filter from it (model/rendering.py).
        self.training_focal = train_setup.training_focal(self.scene)
        self.background = train_setup.resolve_background(cfg.train.background, self.scene, self.device)
        # train.steps=auto: the run is bounded by schedule.max_steps (its learning-rate horizon) and ends when
        # train/schedule.py's rule says so; the strategy and the loop apply its decisions.
        # train.steps=by_views counts the scene's training views (train/steps_by_views.py).
        self.auto_steps = cfg.train.steps == "auto"
        self.max_steps = int(cfg.schedule.max_steps) if self.auto_steps else fixed_steps(cfg.train.steps,
                                                                                         len(self.scene.train))

    def _build_model(self, cfg: Config, state: Optional[dict], model: Optional[GaussianModel]) -> None:
        """The model: from the checkpoint, the caller, or the config's initialisation."""
        model_device = self._model_device()
        if state is not None:
            self.model, self.init_source = self.checkpointer.model_from(state, model_device), "checkpoint"
        elif model is not None:
            self.model, self.init_source = model.to(model_device), "given"
        else:
            self.model, self.init_source = self.ranks.rank0_first(  # triangulated points are cached
                lambda: train_setup.build_model(self.scene, cfg, model_device), "building the initial model")
        if self.model.kind != cfg.model.kind:
            raise ValueError(f"model.kind: config says {cfg.model.kind!r} but the model is {self.model.kind!r}")
        if cfg.strategy.absgrad and (self.model.kind != "gaussians" or self.model_parallel):
            raise ValueError("strategy.absgrad: 3D Gaussians trained in one process or data-parallel only (surfels "
                             "densify from means.grad; model-parallel renders keep their own probe)")

    def _set_up_extensions(self, cfg: Config, extensions: Iterable[Extension],
                           callbacks: Iterable[Callable]) -> None:
        """Extensions (the config's, the caller's and the callbacks) and what they add; every rank starts alike."""
        # Extension points: extras rendered through `features`, extra modules with their own optimizer.
        self.feature_names: List[str] = [n for n in cfg.model.features]
        self.modules = nn.ModuleDict()
        self._module_lrs: Dict[str, float] = {}
        self.extensions: List[Extension] = [build_extension(n, o) for n, o in cfg.extensions.items()]
        self.extensions += list(extensions) + [CallbackExtension(fn) for fn in callbacks]
        for ext in self.extensions:
            ext.setup(self)
        if self.ranks.enabled:  # every rank starts from rank 0's values (the same as one process would)
            self.model = sync_model(self.ranks, self.model, self._model_device(), via=self.device)
            with torch.no_grad():
                for name, p in self.modules.named_parameters():
                    self.ranks.broadcast_(p.data, what=f"broadcasting the initial modules.{name}")

    def _build_optimizers(self, cfg: Config) -> None:
        """Adam for the model (and the extension modules), the batch's learning-rate scaling, the strategy."""
        self.optimizer = build_optimizer(self.model, cfg.optim, self.extent)
        self.module_optimizer = None
        if len(self.modules):
            groups = [{"params": list(m.parameters()), "lr": self._module_lrs[n], "name": n}
                      for n, m in self.modules.items()]
            # The model's rule (optim.adam_kernel): fused on CUDA, which also lets the NaN guard defer (train/guard.py).
            on_cuda = all(p.is_cuda for g in groups for p in g["params"])
            self.module_optimizer = torch.optim.Adam(groups, lr=0.0, fused=fused_adam(cfg.optim.adam_kernel,
                                                                                        on_cuda=on_cuda) or None)
        self.lr_scale = lr_scale(self.batch_size, cfg.train.batch_scaling)
        if self.batch_size > 1:
            apply_batch_scaling(self.optimizers, self.base_learning_rates(), batch_size=self.batch_size,
                                rule=cfg.train.batch_scaling)
        # strategy.unpool_every=auto counts the scene's training views (train/unpool.py), as the prior points do
        strategy_cfg = replace(cfg.strategy, unpool_every=unpool_every_for(cfg.strategy.unpool_every,
                                                                          len(self.scene.train)))
        self.strategy = DensifyStrategy(strategy_cfg, self.extent, invisible_below=cfg.train.alpha_min,
                                        world_extent=cfg.train.scene_extent or scene_content_extent(self.scene),
                                        run_steps=self.max_steps)
        self.strategy.initialize(self.model)

    def _set_up_views_and_evaluation(self, cfg: Config) -> None:
        """Training views (and train.steps=auto's validation split), the virtual views (train.virtual_views), the
        evaluator, counters and the lock."""
        self.views = TrainViews(self.scene, self.device, seed=cfg.train.seed, preload=cfg.data.preload)
        self.scaled_views = ScaledViews(cfg.train.resolution_schedule)  # train.resolution_schedule (coarse to fine)
        if self.auto_steps:  # validation views from the training views (never the test views)
            self.strategy.schedule.auto = AutoStop(cfg.schedule)
            self.views.hold_out(validation_split(self.scene.train, cfg.schedule.val_nth)[1])
        self.best_state = BestState() if self.auto_steps and cfg.schedule.keep_best else None
        num_views = len(self.scene.train)  # what every few-view "auto" counts (train/few_views.py)
        self.drop_rate = drop_rate_for(cfg.train.drop_rate, num_views)  # train/dropout.py
        if self.drop_rate and self.model_parallel:
            raise ValueError("train.drop_rate: not supported with train.parallel=model (use the default data parallel)")
        self.virtual_views = None  # train.virtual_views: cameras between the training ones (train/virtual_views.py)
        self.virtual_every = virtual_every(cfg.train.virtual_views, num_views)
        if self.virtual_every:
            if self.model_parallel:
                raise ValueError("train.virtual_views: not with train.parallel=model (use the default data parallel)")
            confidence = confidence_for(cfg.model.prior_points_confidence, num_views)
            self.virtual_views = virtual_views_for(self.scene, self.views.indices, confidence, self.device,
                                                   cfg.train.seed)
        self.evaluator = Evaluator(self.scene, cfg.eval, self.device, self.out_dir,
                                   render=lambda v: self.render(v, ("rgb",)).rgb, views=self.views,
                                   ranks=self.ranks, render_round=self._render_round if self.model_parallel else None)
        self.counters = RunCounters()
        self._at_boundary = True
        self.stop_requested = False  # set by the loop on Ctrl-C (distributed runs stop together, see train_step)
        # Held by TrainingLoop over each step: another thread (the train.viewer browser viewer, warpgs/viewer)
        # renders the model only while holding it, so never mid-step.
        self.lock = threading.RLock()
        self.viewer = None

    def _resume_and_share_out(self, cfg: Config, state: Optional[dict]) -> None:
        """Restore a checkpoint's state; under train.parallel=model keep this rank's share; per-rank RNG streams."""
        if state is not None:
            self.checkpointer.restore(state, self.training_state())
            saved = state.get("config", {}).get("train", {})
            if lr_scale(saved.get("batch_size", 1), saved.get("batch_scaling", "sqrt")) != self.lr_scale:
                # Trained with another batch size: the restored Adam groups hold its scaling, not this run's.
                apply_batch_scaling(self.optimizers, self.base_learning_rates(), batch_size=self.batch_size,
                                    rule=cfg.train.batch_scaling)
        self._total_primitives = self.model.num_primitives
        if self.model_parallel:  # built (or resumed) whole, alike on every rank; from here on each keeps its share
            shard_training(self.model, self.optimizer, self.strategy, self.ranks)
            move_training(self.model, self.optimizer, self.strategy, self.device, cfg.optim.adam_kernel)
            # Split samples differ per owner (a checkpoint holds rank 0's generator, so a resume reseeds too).
            self.strategy.generator.manual_seed(self.ranks.derived_seed(cfg.strategy.seed, self.step))
        if self.ranks.enabled:
            # Each rank's own global RNG streams (anything a loss or extension draws), from seed, rank and step;
            # what every rank must agree on (view order, split sampling) has its own seeded generator.
            ckpt.seed_everything(self.ranks.derived_seed(cfg.train.seed, self.step))
