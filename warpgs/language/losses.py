"""PPGS losses (pure torch; registered by name so a config can pick them):

    lang_feature    L_r   rendered latent vs the encoded target map (L1, valid pixels), uncertainty-weighted
    bridge_color    L_c = sum_i ||c_MLP,i - c*_i|| + beta_i ||c*_MLP,i - c_i||      (* = stop-gradient)
    bridge_feature  L_f = sum_i ||f_MLP,i - f*_i|| + beta_i ||f*_MLP,i - f_i||,  beta = beta_u (1 - eps) + eps
    ppgs            L = L_rec / s_rec^2 + log s_rec^2 + L_rf / s_rf^2 + log s_rf^2,
                    L_rec = L1 + w_b L_c,  L_rf = L_r + w_b L_f   (learned log s^2; plain sum without them)

c_i is a primitive's view-independent colour (its DC SH coefficient as RGB), f_i its language latent. In each
bidirectional term the first part trains the MLP (and, through it, the centres), the second pulls the
primitive's own value toward the MLP's prediction. The alternating schedule keeps one branch's MLP part frozen
(detached) while the other trains, swapping every `alternate_period` steps; the pulls on the primitives stay on.
Before `bridge_start` only the MLP parts act (with the centres detached). The gradient the MLP parts send into
the centres is multiplied by `bridge_position_scale` (1 = the literal objective; see docs/language.md for why
the default is 0.01).

Losses read their options and helpers from batch["language"] (a `LanguageContext`, set by the trainer
extension); without one, `LanguageConfig()` defaults apply. Modules come from batch["modules"]: "bridge"
(BridgeMLP) and "ppgs_sigma" (HomoscedasticWeights).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Optional, Tuple

import torch
from torch import nn

from warpgs.losses.registry import batch_field, register_loss, render_output
from warpgs.language.settings import LanguageConfig
from warpgs.train.step_info import DeviceFloats

SH_C0 = 0.28209479177387814
BRIDGE_MODULE = "bridge"
SIGMA_MODULE = "ppgs_sigma"


@dataclass
class LanguageContext:
    """What the losses need besides the render and the model: options and the rendered-feature layout."""

    config: LanguageConfig = field(default_factory=LanguageConfig)
    latent_slice: Optional[slice] = None  # channels of render_out.features holding the latent (None: the first dim)
    eps_channel: Optional[int] = None  # channel holding the rendered uncertainty (None: not rendered)
    # The last ppgs call's component values, as detached 0-d tensors (a float() each would be a host read per
    # term per step on a GPU); `last_terms` gives them as floats.
    term_values: Dict[str, torch.Tensor] = field(default_factory=dict)

    @property
    def last_terms(self) -> Dict[str, float]:
        """The last ppgs call's component values as floats (one read for all of them)."""
        return DeviceFloats(self.term_values).read()


# ----- building blocks ----------------------------------------------------------------------------------------
def safe_norm(x: torch.Tensor) -> torch.Tensor:
    """||x||_2 over the last axis with a zero (not NaN) gradient at x = 0."""
    return torch.sqrt((x * x).sum(-1).clamp_min(1e-20))


def beta_from_uncertainty(eps: torch.Tensor, beta_u: float = 0.1) -> torch.Tensor:
    """beta = beta_u (1 - eps) + eps: beta_u for stable primitives (eps = 0), 1 for uncertain ones."""
    return beta_u * (1.0 - eps) + eps


def bidirectional_loss(mlp_out: torch.Tensor, params: torch.Tensor, beta, *, train_mlp: bool = True,
                       reduction: str = "sum", pull: bool = True) -> torch.Tensor:
    """sum_i ||mlp_i - params*_i|| + beta_i ||mlp*_i - params_i||  (* = detached). train_mlp=False detaches the
    first part too (the frozen branch of the alternating schedule): only the pull on `params` remains."""
    if mlp_out.shape != params.shape:
        raise ValueError(f"bidirectional_loss: MLP output {list(mlp_out.shape)} vs parameters {list(params.shape)}")
    pull_mlp = safe_norm(mlp_out - params.detach())
    if not train_mlp:
        pull_mlp = pull_mlp.detach()
    beta = torch.as_tensor(beta, dtype=params.dtype, device=params.device).reshape(-1)
    pull_param = beta * safe_norm(mlp_out.detach() - params)
    if not pull:
        pull_param = pull_param.detach()
    per = pull_mlp + pull_param
    if per.numel() == 0:
        return params.sum() * 0.0
    return per.sum() if reduction == "sum" else per.mean()


def active_branch(step: int, period: int) -> str:
    """"both" (period 0), else "color" for the first `period` steps, then "language", and so on."""
    if period <= 0:
        return "both"
    return "color" if (int(step) // int(period)) % 2 == 0 else "language"


class HomoscedasticWeights(nn.Module):
    """Learned task weighting (Kendall et al.): sum_t L_t exp(-s_t) + s_t with s_t = log sigma_t^2."""

    def __init__(self, num_tasks: int = 2, init: float = 0.0):
        super().__init__()
        self.log_vars = nn.Parameter(torch.full((int(num_tasks),), float(init)))

    def forward(self, *losses: torch.Tensor) -> torch.Tensor:
        if len(losses) != self.log_vars.numel():
            raise ValueError(f"HomoscedasticWeights: {self.log_vars.numel()} tasks, got {len(losses)} losses")
        s = self.log_vars
        return sum(loss * torch.exp(-s[i]) + s[i] for i, loss in enumerate(losses))

    @property
    def sigma2(self) -> torch.Tensor:
        return torch.exp(self.log_vars.detach())


# ----- access helpers -----------------------------------------------------------------------------------------
def context(batch) -> LanguageContext:
    ctx = batch.get("language") if isinstance(batch, dict) else getattr(batch, "language", None)
    return ctx if isinstance(ctx, LanguageContext) else LanguageContext()


def _module(batch, name: str, required: bool = True):
    modules = batch.get("modules") if isinstance(batch, dict) else getattr(batch, "modules", None)
    if modules is not None and name in modules:
        return modules[name]
    if required:
        raise ValueError(f"batch: no {name!r} module (enable it with extensions.language.{'bridge' if name == BRIDGE_MODULE else 'joint'}: true)")
    return None


def primitive_colors(model) -> torch.Tensor:
    """[N, 3] view-independent colour of every primitive: its DC SH coefficient as RGB."""
    return model.params["sh0"][:, 0, :] * SH_C0 + 0.5


def primitive_uncertainty(model, cfg: LanguageConfig) -> Optional[torch.Tensor]:
    """[N] eps = sigmoid(param), or None when the model has no uncertainty parameter."""
    if cfg.uncertainty_name not in model.params:
        return None
    return torch.sigmoid(model.params[cfg.uncertainty_name][:, 0])


class _ScaleGradient(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, scale):
        ctx.scale = scale
        return x.view_as(x)

    @staticmethod
    def backward(ctx, g):
        return g * ctx.scale, None


def scale_gradient(x: torch.Tensor, scale: float) -> torch.Tensor:
    """Identity in the forward pass; multiplies the gradient by `scale` in the backward pass."""
    return _ScaleGradient.apply(x, float(scale))


def bridge_outputs(batch, model, step: int = 0) -> Tuple[Optional[torch.Tensor], Optional[torch.Tensor]]:
    """(c_MLP [N,3], f_MLP [N,d]) for the model's centres; computed once per batch (cached in it)."""
    bridge = _module(batch, BRIDGE_MODULE)
    cfg = context(batch).config
    means = model.params["means"]
    key = ("_bridge_out", id(means), means._version, int(step))
    cache = batch.get("_bridge_cache") if isinstance(batch, dict) else None
    if cache is not None and cache[0] == key:
        return cache[1]
    if not cfg.bridge_position_grad or step < cfg.bridge_start:
        x = means.detach()
    elif cfg.bridge_position_scale != 1.0:
        x = scale_gradient(means, cfg.bridge_position_scale)
    else:
        x = means
    out = bridge(x)
    if isinstance(batch, dict):
        batch["_bridge_cache"] = (key, out)
    return out


def _beta(model, cfg: LanguageConfig, n: int, like: torch.Tensor) -> torch.Tensor:
    eps = primitive_uncertainty(model, cfg)
    if eps is None:
        return torch.full((n,), float(cfg.beta_u), dtype=like.dtype, device=like.device)
    return beta_from_uncertainty(eps if cfg.beta_grad else eps.detach(), cfg.beta_u)


def color_bridge_loss(batch, model, step: int) -> torch.Tensor:
    """L_c (unweighted)."""
    ctx = context(batch)
    c_mlp, _ = bridge_outputs(batch, model, step)
    if c_mlp is None:
        raise ValueError("bridge_color: the bridge has no colour head (extensions.language.bridge_color: true)")
    colors = primitive_colors(model)
    return bidirectional_loss(c_mlp, colors, _beta(model, ctx.config, colors.shape[0], colors),
                              train_mlp=active_branch(step, ctx.config.alternate_period) != "language",
                              reduction=ctx.config.reduction, pull=step >= ctx.config.bridge_start)


def feature_bridge_loss(batch, model, step: int) -> torch.Tensor:
    """L_f (unweighted)."""
    ctx = context(batch)
    cfg = ctx.config
    _, f_mlp = bridge_outputs(batch, model, step)
    if f_mlp is None:
        raise ValueError("bridge_feature: the bridge has no language head (extensions.language.bridge_language: true)")
    latents = model.params[cfg.latent_name]
    return bidirectional_loss(f_mlp, latents, _beta(model, cfg, latents.shape[0], latents),
                              train_mlp=active_branch(step, cfg.alternate_period) != "color",
                              reduction=cfg.reduction, pull=step >= cfg.bridge_start)


def rendered_feature_loss(render_out, batch) -> torch.Tensor:
    """L_r: mean over valid pixels of |F - F*| (mean over latent channels), with the rendered uncertainty U
    (when present) as (1 - w U) |F - F*| + w rho U."""
    ctx = context(batch)
    cfg = ctx.config
    feats = render_output(render_out, "features")
    target = batch_field(batch, "lang_target").to(feats)
    sl = ctx.latent_slice if ctx.latent_slice is not None else slice(0, target.shape[-1])
    pred = feats[..., sl]
    if pred.shape != target.shape:
        raise ValueError(f"batch.lang_target: shape {list(target.shape)} does not match the rendered latent "
                         f"{list(pred.shape)}")
    err = (pred - target).abs().mean(-1, keepdim=True)
    if ctx.eps_channel is not None and cfg.uncertainty_weight > 0:
        u = feats[..., ctx.eps_channel:ctx.eps_channel + 1].clamp(0.0, 1.0)
        w = cfg.uncertainty_weight
        err = (1.0 - w * u) * err + w * cfg.uncertainty_reg * u
    valid = batch.get("lang_valid") if isinstance(batch, dict) else None
    if valid is None:
        return err.mean()
    valid = valid.to(err.dtype)
    return (err * valid).sum() / valid.sum().clamp_min(1.0)


def photometric_loss(render_out, batch, dssim_weight: float = 0.0) -> torch.Tensor:
    pred = render_output(render_out, "rgb")
    target = batch_field(batch, "image").to(pred)
    loss = (pred - target).abs().mean()
    if dssim_weight > 0:
        from warpgs.metrics.image import ssim

        loss = (1.0 - dssim_weight) * loss + dssim_weight * (1.0 - ssim(pred, target))
    return loss


def joint_loss(render_out, batch, model, step: int) -> torch.Tensor:
    """The full PPGS objective (see the module docstring); the bridge and sigma parts are used when their
    modules exist. Component values go to batch["language"].last_terms."""
    ctx = context(batch)
    cfg = ctx.config
    l_photo = photometric_loss(render_out, batch, cfg.dssim_weight)
    l_r = rendered_feature_loss(render_out, batch)
    l_rec, l_rf = l_photo, l_r
    terms = {"l1": l_photo.detach(), "l_r": l_r.detach()}
    bridge = _module(batch, BRIDGE_MODULE, required=False)
    if bridge is not None and cfg.bridge_weight > 0:
        if bridge.color_head is not None:
            l_c = color_bridge_loss(batch, model, step)
            l_rec = l_rec + cfg.bridge_weight * l_c
            terms["l_c"] = l_c.detach()
        if bridge.lang_head is not None:
            l_f = feature_bridge_loss(batch, model, step)
            l_rf = l_rf + cfg.bridge_weight * l_f
            terms["l_f"] = l_f.detach()
    sigma = _module(batch, SIGMA_MODULE, required=False)
    if sigma is not None:
        total = sigma(l_rec, l_rf)
        s2 = sigma.sigma2
        terms["sigma2_rec"], terms["sigma2_rf"] = s2[0].detach(), s2[1].detach()
    else:
        total = l_rec + l_rf
    terms["l_rec"], terms["l_rf"] = l_rec.detach(), l_rf.detach()
    ctx.term_values = {k: v.reshape(()).float() for k, v in terms.items()}
    return total


# ----- registry ---------------------------------------------------------------------------------------------
def _register():
    from warpgs.losses.registry import registered_losses

    if "ppgs" in registered_losses():
        return

    @register_loss("lang_feature", outputs=("features",), weight=1.0)
    def lang_feature(render_out, batch, model, step):
        return rendered_feature_loss(render_out, batch)

    @register_loss("bridge_color", outputs=(), weight=1e-3)
    def bridge_color(render_out, batch, model, step):
        return color_bridge_loss(batch, model, step)

    @register_loss("bridge_feature", outputs=(), weight=1e-3)
    def bridge_feature(render_out, batch, model, step):
        return feature_bridge_loss(batch, model, step)

    @register_loss("ppgs", outputs=("rgb", "features"), weight=1.0)
    def ppgs(render_out, batch, model, step):
        return joint_loss(render_out, batch, model, step)


_register()
