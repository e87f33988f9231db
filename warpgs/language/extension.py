"""The trainer extension `language`: PPGS language fields on the trainer's primitives (surfels or Gaussians).

    imports: [warpgs.language]
    extensions: {language: {dim: 8, bridge: true, joint: true, ...}}   # options: LanguageConfig
    losses: {ppgs: 1.0, l1: 0, dssim: 0}

setup: find (or write the stand-in) features, train or load the scene autoencoder (<out>/language/), add the
latent extra (rendered through `features`), the uncertainty extra (its sigmoid is appended as one more feature
channel), the bridge MLP and the homoscedastic weights as trainer modules. make_batch: the view's encoded target
map (`lang_target` [H,W,d], `lang_valid` [H,W,1]) and the `LanguageContext` the losses read. After the last step:
language_metrics.json (mIoU / mAP of text queries for every label name on the labelled evaluation views).
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import torch

from warpgs.train.extensions import Extension, register_extension
from warpgs.train.step_info import DeviceFloats
from warpgs.language.autoencoder import FeatureAutoencoder
from warpgs.language.bridge import BridgeMLP
from warpgs.language.evaluate import evaluate_language
from warpgs.language.losses import BRIDGE_MODULE, SIGMA_MODULE, HomoscedasticWeights, LanguageContext
from warpgs.language.query import LanguageField
from warpgs.language.settings import EXTENSION_NAME, LanguageConfig
from warpgs.language.targets import TargetMaps, fit_scene_autoencoder, prepare_features, read_meta, write_meta

WORK_DIR = "language"
AE_FILE = "autoencoder.pt"
META_FILE = "meta.json"
METRICS_FILE = "language_metrics.json"


def work_dir(out_dir) -> Path:
    return Path(out_dir) / WORK_DIR


@register_extension(EXTENSION_NAME)
class LanguageFieldExtension(Extension):
    def __init__(self, **options):
        try:
            self.cfg = LanguageConfig(**options)
        except TypeError as e:  # unknown option: list the valid ones
            raise TypeError(f"{e}; options: {sorted(LanguageConfig.__dataclass_fields__)}") from None
        self.ctx = LanguageContext(self.cfg)
        self.targets = None
        self.autoencoder = None
        self.meta = {}
        self.ae_report = None

    # ----- setup ----------------------------------------------------------------------------------------------
    def setup(self, trainer) -> None:
        cfg, model, device = self.cfg, trainer.model, trainer.device
        wd = work_dir(trainer.out_dir)
        ae_path, meta_path = wd / AE_FILE, wd / META_FILE
        if ae_path.is_file() and meta_path.is_file():
            self.autoencoder = FeatureAutoencoder.load(ae_path, device)
            self.meta = read_meta(meta_path)
            folder = Path(self.meta["features"])
            if self.autoencoder.latent_dim != cfg.dim:
                raise ValueError(f"extensions.language.dim: {cfg.dim} but {ae_path} has {self.autoencoder.latent_dim}")
        else:
            folder, fmeta = prepare_features(trainer.scene, cfg, wd)
            names = [trainer.scene.cameras[i].name for i in trainer.scene.train]
            t0 = time.perf_counter()
            self.autoencoder, self.ae_report = fit_scene_autoencoder(folder, names, cfg, seed=trainer.config.train.seed,
                                                                     device=device)
            self.autoencoder.save(ae_path)
            encoder = fmeta.get("text_encoder", cfg.text_encoder)
            self.meta = {"features": str(Path(folder).resolve()), "level": cfg.level, "text_encoder": encoder,
                         "clip_model": fmeta.get("clip_model", cfg.clip_model),
                         "clip_checkpoint": cfg.clip_checkpoint or fmeta.get("clip_checkpoint"),
                         "feature_source": fmeta.get("source", "files"), "dim": cfg.dim,
                         "latent_name": cfg.latent_name, "threshold": cfg.threshold,
                         "labels": {str(k): v for k, v in trainer.scene.label_names.items()},
                         "autoencoder": {"steps": self.ae_report.steps, "train_cosine": self.ae_report.train_cosine,
                                         "seconds": round(time.perf_counter() - t0, 3)}}
            write_meta(meta_path, self.meta)
        self.autoencoder.requires_grad_(False)
        self.targets = TargetMaps(folder, self.autoencoder, self.meta.get("level", cfg.level), device)

        n = model.num_primitives
        trainer.add_extra(cfg.latent_name, torch.zeros(n, cfg.dim), lr=cfg.latent_lr)
        if cfg.uncertainty:
            logit = math.log(cfg.uncertainty_init / (1.0 - cfg.uncertainty_init))
            trainer.add_extra(cfg.uncertainty_name, torch.full((n, 1), logit), lr=cfg.uncertainty_lr, render=False)
        if cfg.bridge:
            bridge = BridgeMLP(cfg.dim, n_freqs=cfg.bridge_freqs, width=cfg.bridge_width, depth=cfg.bridge_depth,
                               skip=cfg.bridge_skip, color=cfg.bridge_color, language=cfg.bridge_language)
            bridge.fit_normalisation(model.means)  # restored from the checkpoint when resuming
            trainer.add_module(BRIDGE_MODULE, bridge, lr=cfg.bridge_lr)
        if cfg.joint:
            trainer.add_module(SIGMA_MODULE, HomoscedasticWeights(2, cfg.sigma_init), lr=cfg.sigma_lr)

    # ----- per step -------------------------------------------------------------------------------------------
    def make_batch(self, trainer, view, batch: dict) -> dict:
        slices = batch.get("feature_slices") or trainer.feature_slices
        self.ctx.latent_slice = slices.get(self.cfg.latent_name)
        total = max((s.stop for s in slices.values()), default=0)
        self.ctx.eps_channel = total if self.cfg.uncertainty else None
        batch["language"] = self.ctx
        if getattr(view, "image", None) is not None:
            target, valid = self.targets.get(view.name, view.width, view.height)
            batch["lang_target"], batch["lang_valid"] = target, valid
        return batch

    def render_inputs(self, trainer, inputs: dict, batch: dict, step: int) -> dict:
        if self.cfg.uncertainty and inputs.get("features") is not None:
            eps = torch.sigmoid(trainer.model.params[self.cfg.uncertainty_name])
            inputs["features"] = torch.cat([inputs["features"], eps], 1)
        return inputs

    def after_step(self, trainer, step: int, info: dict) -> None:
        if self.ctx.term_values:
            values = DeviceFloats(self.ctx.term_values)  # read when info["language"] is (train/step_info.py)
            if hasattr(info, "defer"):
                info.defer(("language",), lambda: {"language": values.read()}, values.ready)
            else:
                info["language"] = values.read()
        if self.cfg.eval_at_end and step + 1 == trainer.max_steps:
            self.write_metrics(trainer)

    # ----- evaluation -----------------------------------------------------------------------------------------
    def write_metrics(self, trainer) -> dict:
        field = LanguageField.from_trainer(trainer, self)
        split, views = trainer.eval_views()
        views = [v for v in views if getattr(v, "labels", None) is not None]
        if not views:
            return {}
        result = evaluate_language(field, views, field.label_names, threshold=self.cfg.threshold)
        result.update({"split": split, "step": trainer.step,
                       "terms": dict(self.ctx.last_terms)})
        path = Path(trainer.out_dir) / METRICS_FILE
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(result, indent=1))
        if not trainer.quiet:
            print(f"warpgs: language {split}: mIoU {result['miou']:.3f} mAP {result['map']:.3f} "
                  f"({result['num_queries']} queries) -> {path}")
        return result

    def state_dict(self) -> dict:
        return {"config": self.cfg.to_dict()}
