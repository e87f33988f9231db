"""Trainer extensions: the hooks methods built on the trainer use (depth priors, language fields, ...).

An extension adds what plain 3DGS does not have, without touching the training loop:

    from warpgs.train.extensions import Extension, register_extension

    @register_extension("language")
    class Language(Extension):
        def __init__(self, dim=8):                    # options come from the config's extensions.language
            self.dim = dim
        def setup(self, trainer):                     # before the optimizers are built
            trainer.add_extra("lang", torch.zeros(trainer.model.num_primitives, self.dim), lr=2.5e-3)
            trainer.add_module("bridge", Bridge(), lr=1e-3)
        def render_inputs(self, trainer, inputs, batch, step):
            inputs["colors"] = ...                    # e.g. colours from the bridge
            return inputs

and a config names it: `extensions: {language: {dim: 8}}`. Losses stay in the loss registry; they reach the
trainer's modules through `batch["modules"]` and the per-primitive extras through `model.params[name]`
(rendered ones through `render_out.features[..., batch["feature_slices"][name]]`).

Hook order in one training step: make_batch -> render_inputs -> (render) -> after_render -> losses ->
backward -> optimizer steps -> strategy -> after_step. `outputs()` adds render outputs to every render the
trainer makes (training and evaluation). Built-in: `environment` (warpgs.model.environment), a learned background,
and `exposure` (warpgs.train.exposure), a colour transform per training view.
"""
from __future__ import annotations

from typing import Callable, Dict, Tuple, Type

_EXTENSIONS: Dict[str, Type["Extension"]] = {}


class Extension:
    """Base class: every hook is optional."""

    name = "extension"

    def setup(self, trainer) -> None:
        """Add per-primitive extras (trainer.add_extra) and modules (trainer.add_module); called once, before the
        optimizers are built, also when resuming (add_extra then keeps the restored values)."""

    def outputs(self) -> Tuple[str, ...]:
        """Render outputs this extension needs besides those of the active losses."""
        return ()

    def make_batch(self, trainer, view, batch: dict) -> dict:
        """Add fields to the batch the losses see (called for every training view)."""
        return batch

    def render_inputs(self, trainer, inputs: dict, batch: dict, step: int) -> dict:
        """Edit the rasterizer's keyword inputs (means, quats, scales, opacities, colors, sh_degree, features)."""
        return inputs

    def after_render(self, trainer, out, batch: dict, step: int):
        """Edit the RenderOutput before the losses (and evaluation) see it, e.g. composite a background model.
        Called for every render the trainer makes; return the (possibly modified) output."""
        return out

    def after_step(self, trainer, step: int, info: dict) -> None:
        """After the optimizer and strategy steps (info: loss values, num_primitives, densify report)."""

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


class CallbackExtension(Extension):
    """Wraps a plain `fn(trainer, step, info)` as an after_step hook."""

    name = "callback"

    def __init__(self, fn: Callable):
        self.fn = fn

    def after_step(self, trainer, step: int, info: dict) -> None:
        self.fn(trainer, step, info)


def register_extension(name: str, *, overwrite: bool = False):
    """Class decorator: make an Extension subclass available to configs as `extensions: {name: {...}}`."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"name: expected a non-empty string, got {name!r}")

    def decorate(cls):
        if not (isinstance(cls, type) and issubclass(cls, Extension)):
            raise ValueError(f"extension {name!r}: expected an Extension subclass, got {cls!r}")
        if name in _EXTENSIONS and not overwrite and _EXTENSIONS[name] is not cls:
            raise ValueError(f"name: an extension {name!r} is already registered (pass overwrite=True)")
        _EXTENSIONS[name] = cls
        cls.name = name
        return cls

    return decorate


def registered_extensions() -> list:
    return sorted(_EXTENSIONS)


def build_extension(name: str, options: dict) -> Extension:
    if name not in _EXTENSIONS:
        import difflib

        close = difflib.get_close_matches(name, list(_EXTENSIONS), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ValueError(f"extensions.{name}: no such extension (registered: {registered_extensions()}; "
                         f"list the module that registers it under `imports`){hint}")
    try:
        return _EXTENSIONS[name](**(options or {}))
    except TypeError as e:
        raise ValueError(f"extensions.{name}: bad options {sorted(options or {})}: {e}") from None
