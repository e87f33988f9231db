"""The loss registry: named callables `(render_out, batch, model, step) -> scalar tensor` that declare the
render outputs they read, with a default weight and an optional schedule.

Register with the decorator, pick terms from the config, render only what the picked terms need:

    @register_loss("edge", outputs=("rgb",), weight=0.1)
    def edge(render_out, batch, model, step): ...

    terms = resolve_losses({"l1": 0.8, "dssim": 0.2, "edge": {"weight": 0.05, "schedule": ["exp", 1, 0.01]}})
    outputs = required_outputs(terms)            # -> ("rgb",): pass to the rasterizer
    result = compute_losses(terms, render_out, batch, model, step, max_steps)
    result.total.backward(); log(result.values)

A term's effective weight at a step is `weight * schedule(step, max_steps)`; weight 0 removes the term and
its outputs. Callables written as `(render_out, batch, model)` (no step) are accepted too.
"""
from __future__ import annotations

import inspect
import math
from dataclasses import dataclass
from typing import Callable, Dict, Iterable, List, Mapping, Optional, Tuple, Union

import torch

# Everything a render op can produce (3D Gaussians and surfels); kept here because losses never import
# the render op (that would pull in Warp).
KNOWN_OUTPUTS = ("rgb", "alpha", "depth", "inv_depth", "features", "normal", "median_depth", "distortion")
SCHEDULE_KINDS = ("constant", "linear", "exp")
DEFAULT_LOSSES = {"l1": None, "dssim": None}  # None: the registered default weight and schedule


@dataclass(frozen=True)
class Schedule:
    """Multiplier on a loss weight: `start` until step `begin`, then `kind` interpolation to `end` at step
    `until` (None: the last training step, max_steps), `end` afterwards. `exp` is log-linear (start, end > 0)."""

    kind: str = "constant"
    start: float = 1.0
    end: float = 1.0
    begin: int = 0
    until: Optional[int] = None

    def __post_init__(self):
        if self.kind not in SCHEDULE_KINDS:
            raise ValueError(f"schedule: kind must be one of {SCHEDULE_KINDS}, got {self.kind!r}")
        for name in ("start", "end"):
            if not math.isfinite(float(getattr(self, name))):
                raise ValueError(f"schedule: {name} must be finite, got {getattr(self, name)}")
        if self.kind == "exp" and (self.start <= 0 or self.end <= 0):
            raise ValueError(f"schedule: 'exp' needs start and end > 0, got {self.start}, {self.end} (use 'linear')")
        if self.begin < 0 or (self.until is not None and self.until <= self.begin):
            raise ValueError(f"schedule: need 0 <= begin < until, got begin={self.begin}, until={self.until}")

    def __call__(self, step: int, max_steps: int) -> float:
        if self.kind == "constant":
            return float(self.start)
        until = max_steps if self.until is None else self.until
        if until <= self.begin:
            return float(self.end) if step >= until else float(self.start)
        t = min(max((step - self.begin) / (until - self.begin), 0.0), 1.0)
        if self.kind == "linear":
            return float(self.start + (self.end - self.start) * t)
        return float(math.exp(math.log(self.start) * (1.0 - t) + math.log(self.end) * t))


ScheduleSpec = Union[None, str, tuple, list, dict, Schedule, Callable[[int, int], float]]


def parse_schedule(spec: ScheduleSpec):
    """None | "constant" | ("exp", start, end[, begin[, until]]) | {"kind": ..., "start": ...} | Schedule |
    callable(step, max_steps) -> multiplier."""
    if spec is None or isinstance(spec, Schedule):
        return spec
    if isinstance(spec, str):
        return Schedule(kind=spec)
    if isinstance(spec, Mapping):
        unknown = set(spec) - {"kind", "start", "end", "begin", "until"}
        if unknown:
            raise ValueError(f"schedule: unknown keys {sorted(unknown)}")
        return Schedule(**spec)
    if isinstance(spec, (tuple, list)):
        if not spec or len(spec) > 5:
            raise ValueError(f"schedule: expected (kind, start, end[, begin[, until]]), got {spec!r}")
        return Schedule(*spec)
    if callable(spec):
        return spec
    raise ValueError(f"schedule: cannot interpret {spec!r}")


@dataclass(frozen=True)
class LossTerm:
    """A registered loss (its defaults) or a configured one (the trainer's active term)."""

    name: str
    fn: Callable
    outputs: Tuple[str, ...]
    weight: float = 1.0
    schedule: Optional[Callable[[int, int], float]] = None
    batch: Tuple[str, ...] = ()  # batch fields it reads that the scene must supply (e.g. "inv_depth_prior")

    def weight_at(self, step: int, max_steps: int) -> float:
        return self.weight * (1.0 if self.schedule is None else float(self.schedule(step, max_steps)))


_REGISTRY: Dict[str, LossTerm] = {}


def _check_weight(name: str, weight) -> float:
    try:
        w = float(weight)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: weight must be a number, got {weight!r}") from None
    if not math.isfinite(w) or w < 0:
        raise ValueError(f"{name}: weight must be finite and >= 0, got {weight!r}")
    return w


def _check_outputs(name: str, outputs) -> Tuple[str, ...]:
    outputs = (outputs,) if isinstance(outputs, str) else tuple(outputs)
    unknown = [o for o in outputs if o not in KNOWN_OUTPUTS]
    if unknown:
        raise ValueError(f"{name}: unknown outputs {unknown}; choose from {KNOWN_OUTPUTS}")
    return outputs


def _with_step(fn: Callable) -> Callable:
    """Accept `(render_out, batch, model)` callables by dropping the step argument."""
    try:
        params = list(inspect.signature(fn).parameters.values())
    except (TypeError, ValueError):
        return fn
    positional = [p for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    if len(positional) == 3 and not any(p.kind == p.VAR_POSITIONAL for p in params):
        def call(render_out, batch, model, step):
            return fn(render_out, batch, model)
        call.__wrapped__ = fn
        return call
    return fn


def register_loss(name: str, outputs: Iterable[str] = ("rgb",), weight: float = 1.0,
                  schedule: ScheduleSpec = None, *, batch: Iterable[str] = (), overwrite: bool = False):
    """Decorator: register `fn(render_out, batch, model, step) -> scalar tensor` under `name`.

    outputs: the render outputs it reads (only these are rendered for it); weight/schedule: defaults that a
    config may override; batch: the batch fields it needs from the scene (the trainer prepares them, e.g. estimates
    depth priors, before the first step). Re-registering a name needs overwrite=True.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"name: expected a non-empty string, got {name!r}")
    label = f"loss {name!r}"
    outs = _check_outputs(label, outputs)
    w = _check_weight(label, weight)
    sched = parse_schedule(schedule)

    def decorate(fn: Callable) -> Callable:
        if not callable(fn):
            raise ValueError(f"{label}: expected a callable, got {fn!r}")
        if name in _REGISTRY and not overwrite:
            raise ValueError(f"name: a loss {name!r} is already registered (pass overwrite=True to replace it)")
        _REGISTRY[name] = LossTerm(name, _with_step(fn), outs, w, sched, tuple(batch))
        return fn

    return decorate


def unregister_loss(name: str) -> None:
    if name not in _REGISTRY:
        raise ValueError(f"name: no loss {name!r} is registered")
    del _REGISTRY[name]


def get_loss(name: str) -> LossTerm:
    if name not in _REGISTRY:
        raise ValueError(f"name: unknown loss {name!r}; registered: {sorted(_REGISTRY)}")
    return _REGISTRY[name]


def registered_losses() -> List[str]:
    return sorted(_REGISTRY)


def resolve_losses(config: Union[None, Mapping[str, object], Iterable[str]] = None) -> List[LossTerm]:
    """Configured terms -> active LossTerms, in config order; weight 0 drops a term.

    config: {name: weight} | {name: {"weight": w, "schedule": spec}} | {name: None} (registered defaults) |
    [names] ; None means DEFAULT_LOSSES (0.8 L1 + 0.2 D-SSIM).
    """
    if config is None:
        config = DEFAULT_LOSSES
    if not isinstance(config, Mapping):
        if isinstance(config, str):
            raise ValueError(f"losses: expected a mapping or a list of names, got the string {config!r}")
        config = {name: None for name in config}
    terms = []
    for name, spec in config.items():
        key = f"losses.{name}"
        if name not in _REGISTRY:
            raise ValueError(f"{key}: unknown loss; registered: {sorted(_REGISTRY)}")
        base = _REGISTRY[name]
        weight, schedule = base.weight, base.schedule
        if isinstance(spec, Mapping):
            unknown = set(spec) - {"weight", "schedule"}
            if unknown:
                raise ValueError(f"{key}: unknown keys {sorted(unknown)} (expected 'weight', 'schedule')")
            weight = _check_weight(key, spec.get("weight", weight))
            if "schedule" in spec:
                try:
                    schedule = parse_schedule(spec["schedule"])
                except ValueError as e:
                    raise ValueError(f"{key}.{e}") from None
        elif spec is not None:
            weight = _check_weight(key, spec)
        if weight > 0:
            terms.append(LossTerm(name, base.fn, base.outputs, weight, schedule, base.batch))
    if not terms:
        raise ValueError("losses: every term has weight 0; nothing to optimise")
    return terms


def required_outputs(terms: Iterable[LossTerm], always: Iterable[str] = ()) -> Tuple[str, ...]:
    """Union of the outputs the (active) terms read, plus `always`, in KNOWN_OUTPUTS order."""
    wanted = set(always)
    for term in terms:
        if term.weight > 0:
            wanted.update(term.outputs)
    return tuple(o for o in KNOWN_OUTPUTS if o in wanted) + tuple(sorted(wanted - set(KNOWN_OUTPUTS)))


def required_batch_fields(terms: Iterable[LossTerm]) -> Dict[str, List[str]]:
    """{batch field: the names of the (active) terms that read it}."""
    needed: Dict[str, List[str]] = {}
    for term in terms:
        if term.weight > 0:
            for field_name in term.batch:
                needed.setdefault(field_name, []).append(term.name)
    return needed


@dataclass
class LossResult:
    total: torch.Tensor  # differentiable weighted sum
    values: Dict[str, torch.Tensor]  # unweighted, detached, per term (terms whose weight is 0 this step: absent)
    weights: Dict[str, float]  # effective weights this step


def compute_losses(terms: Iterable[LossTerm], render_out, batch, model, step: int, max_steps: int) -> LossResult:
    total = None
    values, weights = {}, {}
    for term in terms:
        w = term.weight_at(step, max_steps)
        weights[term.name] = w
        if w == 0.0:
            continue  # scheduled to zero this step: skip the work
        value = term.fn(render_out, batch, model, step)
        if not torch.is_tensor(value) or value.numel() != 1:
            shape = list(value.shape) if torch.is_tensor(value) else type(value).__name__
            raise ValueError(f"loss {term.name!r}: must return a scalar tensor, got {shape}")
        value = value.reshape(())
        values[term.name] = value.detach()
        total = w * value if total is None else total + w * value
    if total is None:
        raise ValueError(f"losses: every term has weight 0 at step {step}")
    return LossResult(total, values, weights)


# ----- helpers for loss authors -----
def render_output(render_out, name: str) -> torch.Tensor:
    """render_out.<name>, with a clear error when the output was not rendered."""
    value = getattr(render_out, name, None)
    if value is None:
        raise ValueError(f"render_out.{name} is None: declare {name!r} in the loss's outputs=(...)")
    return value


def batch_field(batch, key: str) -> torch.Tensor:
    """batch[key] for mappings, batch.<key> for dataclasses/objects."""
    if isinstance(batch, Mapping):
        if key in batch:
            return batch[key]
    elif getattr(batch, key, None) is not None:
        return getattr(batch, key)
    raise ValueError(f"batch: has no {key!r} field")
