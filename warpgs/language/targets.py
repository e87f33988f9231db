"""Training targets: a scene's LangSplat-style features -> the autoencoder -> per-view d-dim latent maps.

`prepare_features` finds (or, for the offline stand-in, writes) the feature folder; `fit_scene_autoencoder`
trains the autoencoder on the training views' segment features; `TargetMaps` encodes each view once and keeps
its [H, W, d] latent map and [H, W, 1] valid mask.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, Sequence, Tuple

import torch

from warpgs.language.autoencoder import AutoencoderConfig, FeatureAutoencoder, train_autoencoder
from warpgs.language.features_io import (collect_features, find_feature_folder, has_view_features,
                                         load_view_features, read_feature_meta, resize_segments)
from warpgs.language.settings import LanguageConfig
from warpgs.language.standin import write_standin_features


def prepare_features(scene, cfg: LanguageConfig, work_dir) -> Tuple[Path, dict]:
    """(feature folder, its metadata). Order: cfg.features if given (must exist); else the scene's
    language_features/; else stand-in features from the label maps, written under work_dir (never into the
    scene folder). A stand-in folder whose settings differ from cfg is rewritten."""
    if cfg.features is not None:
        folder = find_feature_folder(scene.root, cfg.features)
        if folder is None:
            raise FileNotFoundError(f"extensions.language.features: folder {cfg.features!r} not found "
                                    f"(relative paths are taken from the scene folder {scene.root})")
        return folder, read_feature_meta(folder)
    folder = find_feature_folder(scene.root)
    if folder is not None and any(has_view_features(folder, scene.cameras[i].name) for i in scene.train):
        return folder, read_feature_meta(folder)
    if not scene.label_names or not scene.has("labels"):
        raise FileNotFoundError(
            f"{scene.root}: no language features (language_features/<stem>_s.npy + _f.npy) and no label maps "
            f"(labels/<stem>.png + labels.json) to build the offline stand-in from; extract features with "
            f"warpgs.language.clip (pip install warpgs[clip], local weights) or add labels")
    folder = Path(cfg.standin_folder) if cfg.standin_folder else Path(work_dir) / "language_features"
    meta = read_feature_meta(folder)
    wanted = {"source": "standin", "noise": cfg.standin_noise, "seed": cfg.standin_seed}
    if any(meta.get(k) != v for k, v in wanted.items()) or meta.get("views", 0) < 1:
        write_standin_features(scene, folder, noise=cfg.standin_noise, seed=cfg.standin_seed)
        meta = read_feature_meta(folder)
    return folder, meta


def fit_scene_autoencoder(folder, names: Sequence[str], cfg: LanguageConfig, seed: int = 0, device=None):
    """Train the 512 -> dim -> 512 autoencoder on the segment features of these views; (model, report)."""
    names = [n for n in names if has_view_features(folder, n)]
    if not names:
        raise FileNotFoundError(f"{folder}: none of the training views has language features")
    feats = collect_features(folder, names, cfg.level, weighted=True)
    ae_cfg = AutoencoderConfig(in_dim=feats.shape[1], latent_dim=cfg.dim, encoder_hidden=list(cfg.ae_encoder_hidden),
                               decoder_hidden=list(cfg.ae_decoder_hidden))
    return train_autoencoder(feats, steps=cfg.ae_steps, lr=cfg.ae_lr, batch_size=cfg.ae_batch,
                             cos_weight=cfg.ae_cos_weight, seed=seed, device=device, config=ae_cfg)


class TargetMaps:
    """Per-view encoded targets, computed on first use and kept (on `device`)."""

    def __init__(self, folder, autoencoder: FeatureAutoencoder, level: int = 0, device=None):
        self.folder = Path(folder)
        self.autoencoder = autoencoder
        self.level = level
        self.device = device
        self._cache: Dict[str, Tuple[torch.Tensor, torch.Tensor]] = {}

    def has(self, name: str) -> bool:
        return has_view_features(self.folder, name)

    @torch.no_grad()
    def get(self, name: str, width: int, height: int) -> Tuple[torch.Tensor, torch.Tensor]:
        """(target [H, W, d], valid [H, W, 1] bool); all-invalid zeros for a view without features."""
        key = f"{name}@{width}x{height}"
        if key not in self._cache:
            d = self.autoencoder.latent_dim
            if not self.has(name):
                out = (torch.zeros(height, width, d, device=self.device),
                       torch.zeros(height, width, 1, dtype=torch.bool, device=self.device))
            else:
                seg, feats = load_view_features(self.folder, name, self.level)
                seg = resize_segments(seg, width, height)
                ae_device = next(self.autoencoder.parameters()).device
                lat = self.autoencoder.encode(torch.from_numpy(feats).to(ae_device)).to(self.device)
                seg_t = torch.from_numpy(seg).to(self.device)
                valid = seg_t >= 0
                target = torch.zeros(height, width, d, device=self.device)
                target[valid] = lat[seg_t[valid]]
                out = (target, valid[..., None])
            self._cache[key] = out
        return self._cache[key]


def write_meta(path, meta: dict) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(meta, indent=1))


def read_meta(path) -> dict:
    path = Path(path)
    if not path.is_file():
        return {}
    return json.loads(path.read_text())
