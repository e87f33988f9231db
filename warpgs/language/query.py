"""Open-vocabulary queries on a trained language field.

    field = LanguageField.from_run("outputs/synthetic-orbit")        # or .from_trainer(trainer)
    r = field.query(view, "red sphere")       # r.relevancy [H,W] raw, r.normalised, r.mask, r.rgb
    sel = field.select("red sphere")          # [N] bool: primitives whose decoded latent matches
    field.render_rgb(view, keep=~sel)         # "delete";  field.extract(view, sel): only the selection on black
    c = field.click(view, x, y)               # click-to-segment from the rendered feature at pixel (x, y)

Relevancy (LERF / LangSplat): with phi the decoded unit feature, q the query and n_j the canonical phrases
("object", "things", "stuff", "texture"), relevancy = min_j softmax(T phi.q, T phi.n_j)[0], T = 10. Masks follow
LangSplat's protocol: relevancy min-max normalised over the rendered surface to [-1, 1], clipped to [0, 1],
thresholded (0.4 by default); a query whose best pixel is not more relevant than the canonical phrases
(max relevancy <= min_peak) gives an empty mask. Rendered latents are L2-normalised before decoding, since the
autoencoder only saw unit latents (this also undoes partial coverage: F / alpha has the same direction).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Sequence, Union

import numpy as np
import torch
import torch.nn.functional as F

from warpgs.language.autoencoder import FeatureAutoencoder
from warpgs.language.settings import EXTENSION_NAME
from warpgs.language.text import CANONICAL_NEGATIVES, build_text_encoder

Query = Union[str, torch.Tensor, np.ndarray]
SURFACE_ALPHA = 0.5  # pixels with less accumulated opacity count as empty (no relevancy, never in a mask)


@dataclass
class QueryResult:
    relevancy: torch.Tensor  # [H, W] raw relevancy in [0, 1] (0 off the rendered surface)
    normalised: torch.Tensor  # [H, W] LangSplat-normalised relevancy in [0, 1]
    mask: torch.Tensor  # [H, W] bool
    rgb: torch.Tensor  # [H, W, 3] the render
    alpha: torch.Tensor  # [H, W]


def relevancy_scores(features: torch.Tensor, positive: torch.Tensor, negatives: torch.Tensor,
                     temperature: float = 10.0) -> torch.Tensor:
    """[..., C] unit features, [C] query, [K, C] canonical phrases -> [...] relevancy in [0, 1]."""
    pos = features @ positive  # [...]
    neg = features @ negatives.T  # [..., K]
    # softmax over the pair (pos, neg_j), positive entry: sigmoid(T (pos - neg_j)); the worst negative decides.
    return torch.sigmoid(temperature * (pos[..., None] - neg)).min(-1).values


def normalise_relevancy(relevancy: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """LangSplat: (r - min) / (max - min) over valid entries, mapped to [-1, 1], clipped to [0, 1]; 0 elsewhere."""
    out = torch.zeros_like(relevancy)
    if not bool(valid.any()):
        return out
    r = relevancy[valid]
    lo, hi = r.min(), r.max()
    scaled = (relevancy - lo) / (hi - lo).clamp_min(1e-9) * 2.0 - 1.0
    return torch.where(valid, scaled.clamp(0.0, 1.0), out)


class LanguageField:
    """A trained model plus its autoencoder and a text encoder; see the module docstring."""

    def __init__(self, model, autoencoder: FeatureAutoencoder, text_encoder, *, latent_name: str = "lang",
                 background: Optional[torch.Tensor] = None, render_kwargs: Optional[dict] = None,
                 label_names: Optional[Dict[int, str]] = None, negatives: Sequence[str] = CANONICAL_NEGATIVES,
                 temperature: float = 10.0, threshold: float = 0.4, min_peak: float = 0.5):
        if latent_name not in model.params:
            raise ValueError(f"latent_name: the model has no {latent_name!r} parameter (extras: {model.extra_names})")
        if model.params[latent_name].shape[1] != autoencoder.latent_dim:
            raise ValueError(f"{latent_name}: {model.params[latent_name].shape[1]} channels but the autoencoder "
                             f"expects {autoencoder.latent_dim}")
        self.model = model
        self.autoencoder = autoencoder.to(model.device).eval()
        self.text_encoder = text_encoder
        self.latent_name = latent_name
        self.background = background
        self.render_kwargs = dict(render_kwargs or {})
        self.label_names = dict(label_names or {})
        self.temperature = float(temperature)
        self.threshold = float(threshold)
        self.min_peak = float(min_peak)
        self._negatives = self._embed_texts(list(negatives)) if negatives else None
        self.trainer = None  # set by from_trainer / from_run: its other extensions' after_render hooks apply

    # ----- construction -----------------------------------------------------------------------------------------
    @classmethod
    def from_trainer(cls, trainer, extension=None, **kwargs) -> "LanguageField":
        """The field of a trainer with the `language` extension (or of `extension`, that extension itself)."""
        ext = extension or next((e for e in trainer.extensions if getattr(e, "name", None) == EXTENSION_NAME), None)
        if ext is None:
            raise ValueError("trainer: no `language` extension (add extensions: {language: {...}} and "
                             "imports: [warpgs.language] to the config)")
        meta, cfg = ext.meta, ext.cfg
        kind = meta.get("text_encoder", cfg.text_encoder)
        if kind == "clip":
            encoder = build_text_encoder("clip", model_name=meta.get("clip_model") or cfg.clip_model,
                                         checkpoint=meta.get("clip_checkpoint") or cfg.clip_checkpoint,
                                         device=trainer.device)
        else:
            encoder = build_text_encoder("hash", ext.autoencoder.in_dim)
        names = dict(trainer.scene.label_names) or {int(k): v for k, v in meta.get("labels", {}).items()}
        t = trainer.config.train
        kwargs.setdefault("threshold", cfg.threshold)
        field = cls(trainer.model, ext.autoencoder, encoder, latent_name=cfg.latent_name,
                    background=trainer.background, label_names=names,
                    render_kwargs=t.render_options(), **kwargs)
        field.trainer = trainer
        return field

    @classmethod
    def from_run(cls, run_dir, device: Optional[str] = None, **kwargs) -> "LanguageField":
        from warpgs.cli.commands import load_run

        return cls.from_trainer(load_run(run_dir, device), **kwargs)

    # ----- embeddings -------------------------------------------------------------------------------------------
    def _embed_texts(self, texts: Sequence[str]) -> torch.Tensor:
        emb = torch.as_tensor(self.text_encoder.encode(list(texts))).float().to(self.model.device)
        return F.normalize(emb, dim=-1)

    def embedding(self, query: Query) -> torch.Tensor:
        """[C] unit query embedding from a phrase or a given vector."""
        if isinstance(query, str):
            return self._embed_texts([query])[0]
        v = torch.as_tensor(np.asarray(query) if isinstance(query, np.ndarray) else query).float().reshape(-1)
        if v.numel() != self.autoencoder.in_dim:
            raise ValueError(f"query embedding: expected {self.autoencoder.in_dim} values, got {v.numel()}")
        if not torch.isfinite(v).all() or float(v.norm()) == 0:
            raise ValueError("query embedding: must be finite and non-zero")
        return F.normalize(v.to(self.model.device), dim=0)

    @torch.no_grad()
    def decode(self, latents: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
        """[..., d] rendered or per-primitive latents -> [..., C] unit features (latents normalised first)."""
        flat = F.normalize(latents.reshape(-1, latents.shape[-1]).float(), dim=-1, eps=1e-8)
        out = [self.autoencoder.decode(flat[i:i + chunk]) for i in range(0, flat.shape[0], chunk)]
        out = torch.cat(out) if out else flat.new_zeros(0, self.autoencoder.in_dim)
        return out.reshape(*latents.shape[:-1], -1)

    def scores(self, features: torch.Tensor, query: Query) -> torch.Tensor:
        """Relevancy of decoded unit features [..., C] to the query."""
        pos = self.embedding(query)
        if self._negatives is None:
            return features @ pos
        return relevancy_scores(features, pos, self._negatives, self.temperature)

    # ----- rendering --------------------------------------------------------------------------------------------
    @torch.no_grad()
    def render(self, view, outputs: Sequence[str] = ("rgb", "alpha", "features"),
               keep: Optional[torch.Tensor] = None, background: Optional[torch.Tensor] = None,
               composite: bool = True):
        """Render the model (latent as `features`); keep [N] bool hides the other primitives. With a trainer,
        composite=True lets its other extensions finish the image (e.g. the learned environment behind it)."""
        from warpgs.model.rendering import render_model

        outputs = tuple(outputs)
        if "rgb" in outputs and "alpha" not in outputs:
            outputs += ("alpha",)
        inputs = self.model.render_inputs()
        if keep is not None:
            keep = torch.as_tensor(keep, device=self.model.device).reshape(-1)
            if keep.numel() != self.model.num_primitives:
                raise ValueError(f"keep: expected {self.model.num_primitives} entries, got {keep.numel()}")
            inputs["opacities"] = inputs["opacities"] * keep.to(inputs["opacities"].dtype)
        features = self.model.params[self.latent_name] if "features" in outputs else None
        bg = self.background if background is None else background
        out = render_model(self.model, view.viewmat, view.K, view.width, view.height, outputs=outputs,
                           background=bg, features=features, inputs=inputs, **self.render_kwargs)
        if composite and self.trainer is not None and out.rgb is not None:
            out = self._after_render(view, out)
        return out

    def _after_render(self, view, out):
        others = [e for e in self.trainer.extensions if getattr(e, "name", None) != EXTENSION_NAME]
        if not others:
            return out
        batch = {"width": view.width, "height": view.height, "viewmat": view.viewmat, "K": view.K,
                 "name": view.name, "background": self.background, "modules": self.trainer.modules}
        for ext in others:
            out = ext.after_render(self.trainer, out, batch, self.trainer.step)
        return out

    def render_rgb(self, view, keep: Optional[torch.Tensor] = None) -> torch.Tensor:
        """[H, W, 3]; with keep=~selection this is "delete"."""
        return self.render(view, ("rgb",), keep=keep).rgb.clamp(0, 1)

    def delete(self, view, selection: torch.Tensor) -> torch.Tensor:
        """The view rendered without the selected primitives."""
        return self.render_rgb(view, keep=~torch.as_tensor(selection, dtype=torch.bool, device=self.model.device))

    def extract(self, view, selection: torch.Tensor) -> torch.Tensor:
        """Only the selected primitives, on black."""
        sel = torch.as_tensor(selection, dtype=torch.bool, device=self.model.device)
        black = torch.zeros(3, device=self.model.device)
        return self.render(view, ("rgb",), keep=sel, background=black, composite=False).rgb.clamp(0, 1)

    # ----- 2D queries -------------------------------------------------------------------------------------------
    @torch.no_grad()
    def feature_map(self, view):
        """(decoded features [H, W, C], surface [H, W] bool, render)."""
        out = self.render(view)
        surface = out.alpha[..., 0] >= SURFACE_ALPHA
        return self.decode(out.features), surface, out

    @torch.no_grad()
    def query(self, view, query: Query, threshold: Optional[float] = None) -> QueryResult:
        feats, surface, out = self.feature_map(view)
        return self._result(self.scores(feats, query), surface, out, threshold)

    def _result(self, rel, surface, out, threshold) -> QueryResult:
        rel = torch.where(surface, rel, torch.zeros_like(rel))
        norm = normalise_relevancy(rel, surface)
        thr = self.threshold if threshold is None else float(threshold)
        present = bool(surface.any()) and float(rel[surface].max()) > self.min_peak
        mask = (norm > thr) & surface if present else torch.zeros_like(surface)
        return QueryResult(rel, norm, mask, out.rgb.clamp(0, 1), out.alpha[..., 0])

    @torch.no_grad()
    def click(self, view, x: float, y: float, threshold: float = 0.9) -> QueryResult:
        """Segment from a pixel: cosine similarity of every pixel's (and primitive's, via `select_like`) decoded
        feature to the decoded feature at (x, y); mask = similarity > threshold."""
        feats, surface, out = self.feature_map(view)
        col, row = int(x), int(y)
        if not (0 <= col < view.width and 0 <= row < view.height):
            raise ValueError(f"click: pixel ({x}, {y}) is outside the {view.width}x{view.height} view")
        if not bool(surface[row, col]):
            raise ValueError(f"click: pixel ({x}, {y}) shows no surface (alpha < {SURFACE_ALPHA})")
        ref = feats[row, col]
        sim = torch.where(surface, feats @ ref, torch.zeros(1, device=feats.device))
        mask = (sim > threshold) & surface
        return QueryResult(sim.clamp(0, 1), sim.clamp(0, 1), mask, out.rgb.clamp(0, 1), out.alpha[..., 0])

    def clicked_feature(self, view, x: float, y: float) -> torch.Tensor:
        feats, surface, _ = self.feature_map(view)
        return feats[int(y), int(x)]

    # ----- 3D selection -----------------------------------------------------------------------------------------
    @torch.no_grad()
    def primitive_features(self) -> torch.Tensor:
        return self.decode(self.model.params[self.latent_name].detach())

    @torch.no_grad()
    def select(self, query: Query, threshold: Optional[float] = None) -> torch.Tensor:
        """[N] bool: primitives whose decoded latent is relevant to the query (relevancy min-max normalised over
        all primitives as for pixels, then thresholded)."""
        rel = self.scores(self.primitive_features(), query)
        everything = torch.ones_like(rel, dtype=torch.bool)
        norm = normalise_relevancy(rel, everything)
        thr = self.threshold if threshold is None else float(threshold)
        if float(rel.max()) <= self.min_peak:
            return torch.zeros_like(everything)
        return norm > thr

    @torch.no_grad()
    def select_like(self, feature: torch.Tensor, threshold: float = 0.9) -> torch.Tensor:
        """[N] bool: primitives whose decoded latent has cosine > threshold with `feature` (e.g. a clicked one)."""
        return (self.primitive_features() @ F.normalize(feature.float(), dim=0)) > threshold
