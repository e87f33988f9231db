"""The trainer: data -> model -> render op -> losses -> optimizer step -> strategy, driven by a Config.

    from warpgs import Trainer, load_config
    result = Trainer(load_config("configs/default.yaml", ["steps=500"])).fit()
    result.metrics["psnr"], result.out_dir

One step: pick the next training view (a seeded random order, reshuffled every epoch), set the active SH degree
and the position learning rate, render exactly the outputs the active losses (and extensions) declare, sum the
weighted losses, backward, step Adam, let the densification strategy clone/split/prune under its hard budget.

Output folder: config.yaml (the resolved config), checkpoint.pt (atomic; model, optimizer, strategy, RNG
states, step), point_cloud.ply (3DGS layout; surfels in the 2DGS layout), renders/<split>/*.png and
metrics.json. `Trainer(config, resume=True)` continues from the checkpoint to the same result as an
uninterrupted run (bit-exact on CPU). Ctrl-C stops at the end of the current step and writes a checkpoint
there (a second Ctrl-C aborts at once; the previous checkpoint is then kept as it was). A non-finite loss,
gradient or parameter stops training with `NonFiniteError` naming the first offender; the last checkpoint is
left as it was.
"""
from __future__ import annotations

import importlib
import importlib.util
import math
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, Iterable, List, Optional, Sequence, Union

import torch
from torch import nn

from warpgs import checkpoint as ckpt
from warpgs.config import Config, load_config
from warpgs.evaluate import evaluate_views, write_json
from warpgs.extensions import CallbackExtension, Extension, build_extension
from warpgs.gaussians import GaussianModel, atomic_write_bytes
from warpgs.losses import compute_losses, registered_losses, required_outputs, resolve_losses
from warpgs.metrics import LPIPSMetric
from warpgs.model_render import check_outputs, render_model
from warpgs.optim import build_optimizer, update_learning_rates
from warpgs.progress import Progress
from warpgs.strategy import DensifyStrategy
from warpgs import environment  # noqa: F401  (registers the built-in "environment" extension)
from warpgs import train_setup

VIEW_FIELDS = ("mask", "inv_depth_prior", "inv_depth_valid", "depth", "labels", "features")


class NonFiniteError(FloatingPointError):
    """Training produced NaN/Inf; `step` and `name` (the first offending parameter or loss term) say where."""

    def __init__(self, step: int, name: str, problem: str):
        self.step, self.name = step, name
        super().__init__(f"step {step}: {problem}")


@dataclass
class TrainResult:
    out_dir: Path
    steps: int
    loss: Optional[float]  # total loss of the last step
    metrics: dict
    train_seconds: float
    num_primitives: int
    history: List[dict] = field(default_factory=list)


class Trainer:
    """See the module docstring. `scene`/`model` override what the config would build; `extensions` are
    Extension objects (added to those the config names); `callbacks` are `fn(trainer, step, info)` called
    after every step."""

    def __init__(self, config: Union[None, str, Path, dict, Config] = None, *, overrides: Sequence[str] = (),
                 scene=None, model: Optional[GaussianModel] = None, extensions: Iterable[Extension] = (),
                 callbacks: Iterable[Callable] = (), resume: bool = False, out_dir=None, quiet: bool = False):
        self.config = load_config(config, overrides)  # a private, checked copy
        cfg = self.config
        self.quiet = quiet
        for module in cfg.imports:  # e.g. modules that register custom losses or extensions
            import_user_module(module)
        self.device = train_setup.resolve_device(cfg.train.device)
        self.terms = _resolve_terms(cfg.losses)

        self.scene = scene if scene is not None else train_setup.load_training_scene(cfg.data)
        if out_dir is not None:
            cfg.output.dir = str(out_dir)
        if cfg.output.dir is None:
            cfg.output.dir = str(Path("outputs") / train_setup.scene_label(cfg.data))
        self.out_dir = Path(cfg.output.dir)
        self.checkpoint_path = self.out_dir / cfg.output.checkpoint
        self.extent = train_setup.scene_extent(self.scene, cfg.train.scene_extent)
        self.background = train_setup.resolve_background(cfg.train.background, self.scene, self.device)
        self.max_steps = cfg.train.steps

        state = None
        if resume:
            if not self.checkpoint_path.is_file():
                raise FileNotFoundError(f"--resume: no checkpoint at {self.checkpoint_path}")
            state = ckpt.load_checkpoint(self.checkpoint_path)
        ckpt.seed_everything(cfg.train.seed)
        if state is not None:
            self.model = GaussianModel.from_dict(state["model"], device=self.device)
            self.init_source = "checkpoint"
        elif model is not None:
            self.model, self.init_source = model.to(self.device), "given"
        else:
            self.model, self.init_source = train_setup.build_model(self.scene, cfg, self.device)
        if self.model.kind != cfg.model.kind:
            raise ValueError(f"model.kind: config says {cfg.model.kind!r} but the model is {self.model.kind!r}")

        # Extension points: extras rendered through `features`, extra modules with their own optimizer.
        self.feature_names: List[str] = [n for n in cfg.model.features]
        self.modules = nn.ModuleDict()
        self._module_lrs: Dict[str, float] = {}
        self.extensions: List[Extension] = [build_extension(n, o) for n, o in cfg.extensions.items()]
        self.extensions += list(extensions) + [CallbackExtension(fn) for fn in callbacks]
        for ext in self.extensions:
            ext.setup(self)

        self.outputs = required_outputs(self.terms, always=[o for e in self.extensions for o in e.outputs()])
        check_outputs(self.model.kind, self.outputs, "losses")
        if "features" in self.outputs and not self.feature_names and not self.extensions:
            raise ValueError("losses: a term needs the 'features' output but the model renders no features "
                             "(add model.features: {name: channels} or an extension)")

        self.optimizer = build_optimizer(self.model, cfg.optim, self.extent)
        self.module_optimizer = None
        if len(self.modules):
            groups = [{"params": list(m.parameters()), "lr": self._module_lrs[n], "name": n}
                      for n, m in self.modules.items()]
            self.module_optimizer = torch.optim.Adam(groups, lr=0.0)
        self.strategy = DensifyStrategy(cfg.strategy, self.extent)
        self.strategy.initialize(self.model)

        self.train_indices = list(self.scene.train)
        self.view_generator = torch.Generator().manual_seed(int(cfg.train.seed))
        self._queue: List[int] = []
        self._views: Dict[int, object] = {}
        self._eval_views: Optional[list] = None
        self._lpips: Optional[LPIPSMetric] = None
        self.step = 0
        self.train_seconds = 0.0
        self.history: List[dict] = []
        self.last_loss: Optional[float] = None
        self._at_boundary = True
        self._checkpoint_step = -1
        if state is not None:
            self._load_state(state)

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

    # ----- one step -------------------------------------------------------------------------------------------
    def view(self, index: int):
        if index not in self._views:
            v = self.scene.view(index, self.device)
            if not self.config.data.preload:
                return v
            self._views[index] = v
        return self._views[index]

    def next_view(self):
        if not self._queue:
            self._queue = torch.randperm(len(self.train_indices), generator=self.view_generator).tolist()
        return self.view(self.train_indices[self._queue.pop(0)])

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
               track_means2d: bool = False, step: Optional[int] = None):
        step = self.step if step is None else step
        batch = self.make_batch(view, step) if batch is None else batch
        t = self.config.train
        extra = [o for e in self.extensions for o in e.outputs() if o not in outputs]
        outputs = tuple(outputs) + tuple(dict.fromkeys(extra))
        out = render_model(self.model, view.viewmat, view.K, view.width, view.height, outputs=outputs,
                           background=self.background, inputs=self.render_inputs(batch, step, outputs),
                           track_means2d=track_means2d, check_inputs=not t.nan_guard, **t.render_options())
        for ext in self.extensions:
            out = ext.after_render(self, out, batch, step)
        return out

    def outputs_at(self, step: int) -> tuple:
        """The outputs rendered at this step: those of the terms whose scheduled weight is not 0 now, plus the
        extensions' (self.outputs is the union over the whole run)."""
        if all(t.schedule is None for t in self.terms):
            return self.outputs
        live = [t for t in self.terms if t.weight_at(step, self.max_steps) > 0]
        return required_outputs(live, always=[o for e in self.extensions for o in e.outputs()])

    def train_step(self) -> dict:
        """One optimisation step at self.step; returns info for logging and hooks."""
        cfg, model, step = self.config, self.model, self.step
        self._at_boundary = False
        t0 = time.perf_counter()
        view = self.next_view()
        batch = self.make_batch(view, step)
        model.active_sh_degree = train_setup.active_sh_degree(step, cfg, model.max_sh_degree)
        update_learning_rates(self.optimizer, step, cfg.optim, self.extent, self.max_steps)
        densify = step < cfg.strategy.refine_stop
        out = self.render(view, self.outputs_at(step), batch, track_means2d=densify, step=step)
        result = compute_losses(self.terms, out, batch, model, step, self.max_steps)
        self.strategy.step_pre_backward(model, step)
        result.total.backward()
        if cfg.train.nan_guard:  # before the optimizer step, so nothing non-finite is ever applied
            self.check_finite(step, result)
        for opt in self.optimizers:
            opt.step()
        report = None
        if densify:
            grad2d = out.means2d.grad if out.means2d is not None else None
            report = self.strategy.step_post_backward(model, self.optimizer, step, visible=out.visible,
                                                      viewmat=view.viewmat, K=view.K, width=view.width,
                                                      height=view.height, grad2d=grad2d, near=cfg.train.near)
        for opt in self.optimizers:
            opt.zero_grad(set_to_none=True)
        model.zero_grad(set_to_none=True)
        loss = float(result.total.detach())
        train_psnr = None
        if out.rgb is not None:
            mse = float(((out.rgb.detach() - view.image) ** 2).mean())
            train_psnr = 10.0 * math.log10(1.0 / max(mse, 1e-10))
        self.train_seconds += time.perf_counter() - t0
        self.step = step + 1
        self.last_loss = loss
        self._at_boundary = True
        return {"step": step, "loss": loss, "values": {k: float(v) for k, v in result.values.items()},
                "psnr": train_psnr, "num_primitives": model.num_primitives, "densify": report, "view": view.name}

    # ----- NaN guard ------------------------------------------------------------------------------------------
    def named_parameters(self):
        for name, p in self.model.params.items():
            yield name, p
        for name, p in self.modules.named_parameters():
            yield f"modules.{name}", p

    def check_finite(self, step: int, result=None) -> None:
        """Raise NonFiniteError unless the loss, every gradient and every parameter are finite. Cheap on the
        good path: one sum per tensor (NaN and Inf propagate through it) and one device sync; the names come
        from a second, exact pass only when a sum is not finite. Parameters are checked too because an
        invisible NaN primitive has zero gradient and would otherwise reach a checkpoint unnoticed."""
        named = list(self.named_parameters())
        sums = [p.detach().sum().float() for _, p in named if p.numel()]
        sums += [p.grad.sum().float() for _, p in named if p.grad is not None and p.grad.numel()]
        if result is not None:
            sums.append(result.total.detach().reshape(()).float())
        if not sums or bool(torch.isfinite(torch.stack(sums)).all()):
            return
        name = self._first_nonfinite(grads=False)
        if name is not None:
            raise NonFiniteError(step, name, f"parameter {name!r} is not finite")
        if result is not None and not bool(torch.isfinite(result.total.detach())):
            terms = [n for n, v in result.values.items() if not bool(torch.isfinite(v))]
            label = "/".join(terms) or "total"
            raise NonFiniteError(step, terms[0] if terms else "loss",
                                 f"loss {label} is not finite (all parameters are finite)")
        name = self._first_nonfinite(grads=True)
        if name is not None:
            raise NonFiniteError(step, name, f"gradient of {name!r} is not finite")
        # Only a sum overflowed (finite values beyond float range in total): nothing is actually non-finite.

    def _first_nonfinite(self, grads: bool) -> Optional[str]:
        for name, p in self.named_parameters():
            t = p.grad if grads else p.detach()
            if t is not None and not bool(torch.isfinite(t).all()):
                return name
        return None

    # ----- evaluation -----------------------------------------------------------------------------------------
    def eval_views(self, split: Optional[str] = None) -> tuple:
        """(split actually used, views): the test views, or the training views when there are none."""
        split = split or self.config.eval.split
        idx = self.scene.test if split == "test" else self.scene.train
        if not idx:
            split, idx = "train", self.scene.train
        return split, [self.view(i) if i in self._views else self.scene.view(i, self.device) for i in idx]

    def lpips(self) -> Optional[LPIPSMetric]:
        if not self.config.eval.lpips:
            return None
        if self._lpips is None:
            with torch.random.fork_rng(devices=[]):  # building the net must not shift the training RNG
                self._lpips = LPIPSMetric(self.config.eval.lpips_net, device=self.device)
        return self._lpips

    def evaluate(self, *, save_images: bool = False, max_views: int = 0) -> dict:
        if self._eval_views is None:
            self._eval_views = self.eval_views()
        split, views = self._eval_views
        if max_views:
            views = views[:max_views]
        save_dir = self.out_dir / "renders" / split if save_images else None
        metrics = evaluate_views(lambda v: self.render(v, ("rgb",)).rgb, views, lpips=self.lpips(),
                                 save_dir=save_dir)
        metrics["split"] = split
        return metrics

    # ----- checkpoints ----------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"step": self.step, "model": self.model.to_dict(), "optimizer": self.optimizer.state_dict(),
                "module_optimizer": None if self.module_optimizer is None else self.module_optimizer.state_dict(),
                "modules": self.modules.state_dict(), "strategy": _to_cpu(self.strategy.state_dict()),
                "extensions": {f"{i}:{e.name}": e.state_dict() for i, e in enumerate(self.extensions)},
                "rng": ckpt.rng_state(), "view_generator": self.view_generator.get_state(),
                "view_queue": list(self._queue), "train_seconds": self.train_seconds, "history": self.history,
                "last_loss": self.last_loss, "config": self.config.to_dict()}

    def save_checkpoint(self) -> Path:
        if not self._at_boundary:
            raise RuntimeError("save_checkpoint: only between steps")
        if self.config.train.nan_guard:
            self.check_finite(self.step)  # never replace a good checkpoint with a broken one
        path = ckpt.save_checkpoint(self.checkpoint_path, self.state_dict())
        self._checkpoint_step = self.step
        return path

    def _load_state(self, state: dict) -> None:
        self.step = int(state["step"])
        self.optimizer.load_state_dict(state["optimizer"])
        names = [g.get("name") for g in self.optimizer.param_groups]
        if names != list(self.model.params):
            raise ValueError(f"checkpoint: optimizer groups {names} do not match the model {list(self.model.params)}")
        if state.get("modules"):
            self.modules.load_state_dict(state["modules"])
        if state.get("module_optimizer") is not None and self.module_optimizer is not None:
            self.module_optimizer.load_state_dict(state["module_optimizer"])
        strat = {k: (v.to(self.device) if torch.is_tensor(v) and k != "generator" else v)
                 for k, v in state["strategy"].items()}
        self.strategy.load_state_dict(strat)
        saved_ext = list(state.get("extensions", {}).values())
        for ext, s in zip(self.extensions, saved_ext):
            ext.load_state_dict(s)
        ckpt.set_rng_state(state["rng"])
        self.view_generator.set_state(state["view_generator"])
        self._queue = list(state["view_queue"])
        self.train_seconds = float(state.get("train_seconds", 0.0))
        self.history = list(state.get("history", []))
        self.last_loss = state.get("last_loss")
        self._checkpoint_step = self.step

    # ----- the loop -------------------------------------------------------------------------------------------
    def _say(self, progress: Optional[Progress], message: str) -> None:
        if self.quiet:
            return
        if progress is not None:
            progress.write(message)
        else:
            print(message, file=sys.stderr)

    def fit(self) -> TrainResult:
        threads = self.config.train.threads or (1 if self.device.type == "cpu" else 0)
        previous = torch.get_num_threads()
        if threads:
            # On CPU the Warp kernels spread over their own thread pool; torch's OpenMP workers spinning next to
            # them (and next to any other process) cost far more than they save on these small per-image ops:
            # measured on the 2-core machine with another job running, 0.06-0.15 s a step with 1 thread against
            # 0.7 s with 2 (128x96, 3k Gaussians).
            torch.set_num_threads(threads)
        try:
            return self._fit()
        finally:
            torch.set_num_threads(previous)

    def _fit(self) -> TrainResult:
        cfg = self.config
        self.out_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(self.out_dir / "config.yaml", cfg.to_yaml().encode())
        progress = Progress(self.max_steps, self.step, enabled=cfg.train.progress and not self.quiet,
                            log_every=cfg.train.log_every)
        if self.step == 0 or self.init_source != "checkpoint":
            self._say(progress, f"warpgs: {self.scene.summary()}")
            self._say(progress, f"warpgs: {self.model.num_primitives} {self.model.kind} from {self.init_source}; "
                                f"losses {[t.name for t in self.terms]} render {list(self.outputs)}; "
                                f"{self.max_steps} steps on {self.device}; output {self.out_dir}")
        else:
            self._say(progress, f"warpgs: resuming at step {self.step} from {self.checkpoint_path}")
        ema_loss = ema_psnr = None
        try:
            with _StopOnSigint(lambda m: self._say(progress, m)) as sigint:
                while self.step < self.max_steps:
                    if sigint.requested:
                        raise KeyboardInterrupt
                    info = self.train_step()
                    for ext in self.extensions:
                        ext.after_step(self, info["step"], info)
                    ema_loss = info["loss"] if ema_loss is None else 0.9 * ema_loss + 0.1 * info["loss"]
                    if info["psnr"] is not None:
                        ema_psnr = info["psnr"] if ema_psnr is None else 0.9 * ema_psnr + 0.1 * info["psnr"]
                    last = self.history[-1] if self.history else {}
                    progress.update(self.step, loss=ema_loss, psnr=ema_psnr, n=self.model.num_primitives,
                                    test=last.get("psnr"))
                    if cfg.eval.every and self.step % cfg.eval.every == 0 and self.step < self.max_steps:
                        self._periodic_eval(progress)
                    if (cfg.train.checkpoint_every and self.step % cfg.train.checkpoint_every == 0
                            and self.step < self.max_steps):
                        self.save_checkpoint()
        except KeyboardInterrupt:
            progress.close()
            if self._at_boundary and self.step != self._checkpoint_step:
                try:
                    self.save_checkpoint()
                    self._say(None, f"warpgs: interrupted; checkpoint at step {self.step} in "
                                    f"{self.checkpoint_path} (continue with --resume)")
                except KeyboardInterrupt:
                    self._say(None, "warpgs: interrupted again while saving; the previous checkpoint is intact")
            else:
                kept = (f"the checkpoint of step {self._checkpoint_step} in {self.checkpoint_path} is intact"
                        if self._checkpoint_step >= 0 else "no checkpoint was written yet")
                self._say(None, f"warpgs: interrupted during step {self.step}; {kept}")
            raise
        except NonFiniteError as e:
            progress.close()
            kept = (f"last good checkpoint: step {self._checkpoint_step} in {self.checkpoint_path}"
                    if self._checkpoint_step >= 0 else "no checkpoint was written")
            self._say(None, f"warpgs: stopped, {e}; {kept}")
            raise
        progress.close()
        return self.finish()

    def _periodic_eval(self, progress: Progress) -> None:
        m = self.evaluate(max_views=self.config.eval.max_views)
        entry = {"step": self.step, "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"],
                 "num_primitives": self.model.num_primitives, "train_seconds": round(self.train_seconds, 3)}
        self.history.append(entry)
        lp = f" lpips {m['lpips']:.4f}" if m["lpips"] is not None else ""
        self._say(progress, f"[eval {m['split']} @ {self.step}] psnr {m['psnr']:.2f} ssim {m['ssim']:.4f}{lp} "
                            f"n {self.model.num_primitives} ({self.train_seconds:.1f} s)")

    def finish(self) -> TrainResult:
        """Final checkpoint, PLY, test renders and metrics.json."""
        cfg = self.config
        if self.step != self._checkpoint_step:
            self.save_checkpoint()
        self.model.save_ply(self.out_dir / cfg.output.ply)
        m = self.evaluate(save_images=cfg.eval.save_images)
        metrics = {"split": m["split"], "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"]}
        if "lpips_unavailable" in m:
            metrics["lpips_unavailable"] = m["lpips_unavailable"]
        metrics.update({"num_primitives": self.model.num_primitives, "steps": self.step,
                        "train_seconds": round(self.train_seconds, 3), "num_views": m["num_views"],
                        "model_kind": self.model.kind, "device": str(self.device), "scene": str(self.scene.root),
                        "final_loss": self.last_loss, "history": self.history, "per_view": m["per_view"]})
        write_json(self.out_dir / cfg.output.metrics, metrics)
        lp = f" lpips {m['lpips']:.4f}" if m["lpips"] is not None else " lpips unavailable"
        self._say(None, f"warpgs: {m['split']} psnr {m['psnr']:.2f} ssim {m['ssim']:.4f}{lp}; "
                        f"{self.model.num_primitives} primitives; {self.step} steps in {self.train_seconds:.1f} s")
        return TrainResult(self.out_dir, self.step, self.last_loss, metrics, self.train_seconds,
                           self.model.num_primitives, list(self.history))


def import_user_module(spec: str):
    """`imports:` entries: a module name (searched on sys.path and in the working directory) or a .py file."""
    if spec.endswith(".py"):
        path = Path(spec)
        if not path.is_file():
            raise ValueError(f"imports: no file {spec!r}")
        name = "warpgs_user_" + path.stem
        if name in sys.modules:
            return sys.modules[name]
        loader_spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(loader_spec)
        sys.modules[name] = module
        try:
            loader_spec.loader.exec_module(module)
        except Exception:
            del sys.modules[name]
            raise
        return module
    try:
        return importlib.import_module(spec)
    except ModuleNotFoundError as e:
        if e.name != spec.split(".")[0] or str(Path.cwd()) in sys.path:
            raise ValueError(f"imports: cannot import {spec!r} ({e})") from None
    sys.path.insert(0, str(Path.cwd()))  # as `python -m` does; console scripts do not
    try:
        return importlib.import_module(spec)
    except ModuleNotFoundError as e:
        raise ValueError(f"imports: cannot import {spec!r} ({e}); give a module on PYTHONPATH or a .py file") from None


def _resolve_terms(losses: dict):
    try:
        return resolve_losses(losses)
    except ValueError as e:
        msg = str(e)
        if "unknown loss" in msg:
            import difflib

            name = msg.split(":", 1)[0].replace("losses.", "")
            close = difflib.get_close_matches(name, registered_losses(), n=1, cutoff=0.5)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ValueError(f"losses.{name}: unknown loss; registered: {registered_losses()} (register your own "
                             f"with warpgs.register_loss and list its module under `imports`){hint}") from None
        raise


def _to_cpu(state: dict) -> dict:
    return {k: (v.detach().cpu() if torch.is_tensor(v) else v) for k, v in state.items()}


class _StopOnSigint:
    """First Ctrl-C: finish the current step, then stop (the trainer checkpoints there). Second: abort now."""

    def __init__(self, say: Callable[[str], None]):
        self.say = say
        self.requested = False
        self._previous = None

    def _handler(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        self.say("warpgs: Ctrl-C: stopping after this step (press again to abort without saving)")

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            try:
                self._previous = signal.signal(signal.SIGINT, self._handler)
            except (ValueError, OSError):
                self._previous = None
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
        return False


def train(config=None, overrides: Sequence[str] = (), **kwargs) -> TrainResult:
    """Shorthand: Trainer(config, overrides=overrides, **kwargs).fit()."""
    return Trainer(config, overrides=overrides, **kwargs).fit()
