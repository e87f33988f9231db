"""Options of the language field (`extensions: {language: {...}}` in a training config)."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import List, Optional

EXTENSION_NAME = "language"  # the trainer extension's registered name: `extensions: {language: {...}}`
REDUCTIONS = ("sum", "mean")
TEXT_ENCODERS = ("hash", "clip")


@dataclass
class LanguageConfig:
    # --- supervision: LangSplat-style .npy per view ---
    features: Optional[str] = None  # folder (relative to the scene or absolute); None: <scene>/language_features,
    #                                  generated from the label maps (offline stand-in) when missing
    level: int = 0  # which level of multi-level segment maps (0: single-level / LangSplat "default")
    standin_noise: float = 0.3  # stand-in only: noise norm added to each segment's name embedding
    standin_seed: int = 0
    standin_folder: Optional[str] = None  # where stand-in features go; None: <output dir>/language_features
    text_encoder: str = "hash"  # "hash" (stand-in) or "clip" (warpgs[clip] with local weights)
    clip_model: str = "ViT-B-16"
    clip_checkpoint: Optional[str] = None  # local open_clip checkpoint file (never downloaded)
    # --- autoencoder 512 -> dim -> 512 ---
    dim: int = 8
    ae_steps: int = 400
    ae_lr: float = 3e-3
    ae_batch: int = 256
    ae_cos_weight: float = 1.0
    ae_encoder_hidden: List[int] = field(default_factory=lambda: [256, 64])  # LangSplat's deeper stack
    ae_decoder_hidden: List[int] = field(default_factory=lambda: [64, 256])  # converges far slower on a CPU
    # --- per-primitive parameters ---
    latent_name: str = "lang"  # extra [N, dim] rendered through `features`
    latent_lr: float = 2.5e-3
    uncertainty: bool = True  # per-primitive eps = sigmoid(param), rendered as one more feature channel
    uncertainty_name: str = "lang_eps"
    uncertainty_init: float = 0.1  # initial eps
    uncertainty_lr: float = 1e-2
    uncertainty_weight: float = 0.5  # L_r per pixel: (1 - w U) |F - F*| + w rho U  (U: rendered eps)
    uncertainty_reg: float = 0.05  # rho: pixels whose latent error exceeds rho raise their primitives' eps
    beta_u: float = 0.1  # beta = beta_u (1 - eps) + eps
    beta_grad: bool = False  # let the bridge losses' beta train eps too (they push it to 0)
    # --- bridge ---
    bridge: bool = True
    bridge_color: bool = True  # colour head (L_c)
    bridge_language: bool = True  # language head (L_f)
    bridge_lr: float = 1e-3
    bridge_weight: float = 1e-3  # weight of L_c and L_f inside the joint loss
    bridge_freqs: int = 10
    bridge_width: int = 96
    bridge_depth: int = 4
    bridge_skip: bool = True
    bridge_position_grad: bool = True  # L_c / L_f move the centres through the MLP (the push-pull)
    bridge_position_scale: float = 0.01  # multiplier on that gradient (1: the paper's literal objective, where it
    #                                      outweighs the photometric gradient of the centres ~50-200x; see docs)
    bridge_start: int = 0  # before this step the MLP only fits the primitives (no pulls, no position gradient)
    reduction: str = "sum"  # over primitives, as the paper's sum; "mean" to make the weight size-independent
    alternate_period: int = 100  # steps per phase of the alternating schedule; 0: both branches every step
    # --- joint (homoscedastic) weighting ---
    joint: bool = True  # L = L_rec / s_rec^2 + log s_rec^2 + L_rf / s_rf^2 + log s_rf^2 (learned log s^2)
    sigma_lr: float = 1e-3
    sigma_init: float = 0.0  # initial log sigma^2
    dssim_weight: float = 0.0  # L_rec's photometric part: (1 - w) L1 + w D-SSIM (the paper: L1 only)
    # --- evaluation at the end of training ---
    eval_at_end: bool = True  # write language_metrics.json (mIoU / mAP on labelled eval views)
    threshold: float = 0.4  # mask threshold on min-max-normalised relevancy (LangSplat's protocol)

    def __post_init__(self):
        if int(self.dim) != self.dim or self.dim < 1:
            raise ValueError(f"dim: expected a positive integer, got {self.dim}")
        if self.reduction not in REDUCTIONS:
            raise ValueError(f"reduction: expected one of {REDUCTIONS}, got {self.reduction!r}")
        if self.text_encoder not in TEXT_ENCODERS:
            raise ValueError(f"text_encoder: expected one of {TEXT_ENCODERS}, got {self.text_encoder!r}")
        if not 0.0 < self.uncertainty_init < 1.0:
            raise ValueError(f"uncertainty_init: expected a value in (0, 1), got {self.uncertainty_init}")
        if not 0.0 <= self.uncertainty_weight <= 1.0:
            raise ValueError(f"uncertainty_weight: expected a value in [0, 1], got {self.uncertainty_weight}")
        if self.alternate_period < 0 or self.level < 0:
            raise ValueError("alternate_period and level must be >= 0")
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"{f.name}: expected a finite number, got {v}")
        for name in ("latent_name", "uncertainty_name"):
            if not getattr(self, name).isidentifier():
                raise ValueError(f"{name}: expected an identifier, got {getattr(self, name)!r}")

    def to_dict(self) -> dict:
        return asdict(self)
