"""Checking a raw mapping into a Config: unknown keys (with close matches), types, ranges, cross-field rules."""
from __future__ import annotations

import dataclasses
import difflib
import math
import os
import typing
from typing import Any, Dict, List, Mapping, Union

from warpgs.render.defaults import LOWEST_TRANSMITTANCE_MIN, alpha_clamp_problem
from warpgs.config.schema import (ALIASES, AUTO_BOOLS, BACKGROUNDS, CHOICES, NON_NEGATIVE, POSITIVE, SECTIONS,
                                  Config, ConfigError, all_keys)


def from_dict(raw: Mapping) -> Config:
    """A nested mapping -> Config; unknown keys and ill-typed values raise ConfigError naming the key."""
    if not isinstance(raw, Mapping):
        raise ConfigError("", f"expected a mapping, got {type(raw).__name__}")
    unknown = [k for k in raw if k not in SECTIONS]
    if unknown:
        k = unknown[0]
        inner = raw[k]
        _unknown_key(f"{k}.{next(iter(inner))}" if isinstance(inner, Mapping) and inner else str(k))
    kwargs = {}
    for name, f in SECTIONS.items():
        if name not in raw:
            continue
        value = raw[name]
        if name == "losses":
            kwargs[name] = _check_losses(value)
        elif name == "imports":
            kwargs[name] = _check_imports(value)
        elif name == "extensions":
            kwargs[name] = _check_extensions(value)
        else:
            kwargs[name] = _build_section(name, f.default_factory, value)
    cfg = Config(**kwargs)
    _check_cross(cfg)
    return cfg


# ----- internals --------------------------------------------------------------------------------------------
def _unknown_key(key: str) -> None:
    candidates = all_keys()
    close = difflib.get_close_matches(key, candidates, n=3, cutoff=0.6)
    if not close:  # also match on the last part ("stepz" -> train.steps)
        last = key.rsplit(".", 1)[-1]
        by_last = {k.rsplit(".", 1)[-1]: k for k in candidates}
        close = [by_last[m] for m in difflib.get_close_matches(last, list(by_last), n=3, cutoff=0.7)]
    named = [f"{c!r} (= {ALIASES[c]})" if c in ALIASES else repr(c) for c in close]
    hint = f"; did you mean {' or '.join(named)}?" if close else ""
    section = key.split(".", 1)[0]
    if section in SECTIONS and not hint:
        fields_ = [k for k in candidates if k.startswith(section + ".")]
        hint = f"; {section} has {', '.join(k.split('.', 1)[1] for k in fields_)}" if fields_ else ""
    raise ConfigError(key, f"unknown config key{hint}")


def _build_section(section: str, factory, value):
    default = factory()
    if value is None:
        return default
    if dataclasses.is_dataclass(value):
        value = dataclasses.asdict(value)
    if not isinstance(value, Mapping):
        raise ConfigError(section, f"expected a mapping of settings, got {value!r}")
    cls = type(default)
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for k, v in value.items():
        key = f"{section}.{k}"
        if k not in names:
            _unknown_key(key)
        kwargs[k] = _check_value(key, v, hints[k])
    try:
        obj = cls(**kwargs)
    except ValueError as e:  # OptimConfig / StrategyConfig checks: "field: problem"
        msg = str(e)
        raise ConfigError(f"{section}.{msg.split(':', 1)[0]}" if ":" in msg else section,
                          msg.split(":", 1)[1].strip() if ":" in msg else msg) from None
    return obj


def _check_value(key: str, value, tp):
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if key == "train.steps":
        return _check_steps(key, value)
    if key == "train.virtual_views":
        return _check_virtual_views(key, value)
    if key == "train.drop_rate":
        return _check_drop_rate(key, value)
    if key == "model.prior_points_confidence":
        return _check_prior_confidence(key, value)
    if key == "strategy.unpool_every":
        return _check_unpool_every(key, value)
    if key in AUTO_BOOLS:
        return _check_auto_bool(key, value)
    if tp is Any:
        value = _check_background(key, value) if key == "train.background" else value
        return value
    if origin is Union:
        if value is None or (isinstance(value, str) and value.lower() in ("none", "null") and type(None) in args):
            if type(None) in args:
                return None
        inner = [a for a in args if a is not type(None)]
        return _check_value(key, value, inner[0]) if len(inner) == 1 else value
    if origin in (dict, Dict):
        if value is None:
            return {}
        if not isinstance(value, Mapping):
            raise ConfigError(key, f"expected a mapping, got {value!r}")
        vt = args[1] if len(args) == 2 else Any
        return {str(k): _check_value(f"{key}.{k}", v, vt) for k, v in value.items()}
    if origin in (list, List):
        if isinstance(value, str) and args == (str,):  # one name, or a list YAML could not read: "[a?.png, b.png]"
            text = value.strip()
            value = ([item.strip().strip("'\"") for item in text[1:-1].split(",") if item.strip()]
                     if text.startswith("[") and text.endswith("]") else [value])
        if not isinstance(value, (list, tuple)):
            raise ConfigError(key, f"expected a list, got {value!r}")
        return list(value)
    if tp is bool:
        return _as_bool(key, value)
    if tp is int:
        out = _as_number(key, value, int)
        if key in POSITIVE and out < 1:
            raise ConfigError(key, f"expected a positive integer, got {value!r}")
        if key in NON_NEGATIVE and out < 0:
            raise ConfigError(key, f"expected a non-negative integer, got {value!r}")
        return out
    if tp is float:
        out = _as_number(key, value, float)
        if not math.isfinite(out):
            raise ConfigError(key, f"expected a finite number, got {value!r}")
        return out
    if tp is str:
        if isinstance(value, bool) or value is None or isinstance(value, (list, dict)):
            raise ConfigError(key, f"expected a string, got {value!r}")
        value = str(value)
        if key in CHOICES and value not in CHOICES[key]:
            close = difflib.get_close_matches(value, CHOICES[key], n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ConfigError(key, f"expected one of {list(CHOICES[key])}, got {value!r}{hint}")
        if key == "train.device":
            _check_device(key, value)
        return value
    return value


def _as_bool(key: str, value) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.lower() in ("true", "yes", "on", "1", "false", "no", "off", "0"):
        return value.lower() in ("true", "yes", "on", "1")
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    raise ConfigError(key, f"expected true or false, got {value!r}")


def _as_number(key: str, value, kind):
    if isinstance(value, bool):
        raise ConfigError(key, f"expected {'an integer' if kind is int else 'a number'}, got {value!r}")
    if isinstance(value, str):  # YAML reads "1e-3" (no dot) as a string
        try:
            value = float(value.strip().replace("_", ""))
        except ValueError:
            raise ConfigError(key, f"expected {'an integer' if kind is int else 'a number'}, got {value!r}") from None
    if not isinstance(value, (int, float)):
        raise ConfigError(key, f"expected {'an integer' if kind is int else 'a number'}, got {value!r}")
    if kind is int:
        if isinstance(value, float) and not (math.isfinite(value) and value == int(value)):
            raise ConfigError(key, f"expected an integer, got {value!r}")
        return int(value)
    return float(value)


def _number_or_auto(key: str, value, kind, fits, expected: str):
    """"auto", or a number of `kind` (int or float) for which fits(number) holds; anything else is an error saying
    `expected`."""
    if isinstance(value, str) and value.strip().lower() == "auto":
        return "auto"
    try:
        number = _as_number(key, value, kind)
    except ConfigError:
        raise ConfigError(key, f"expected {expected} or 'auto', got {value!r}") from None
    if not fits(number):
        raise ConfigError(key, f"expected {expected} or 'auto', got {value!r}")
    return number


def _check_steps(key: str, value):
    """A positive step count, "auto" (train/schedule.py) or "by_views" (train/steps_by_views.py)."""
    if isinstance(value, str) and value.strip().lower() == "by_views":
        return "by_views"
    try:
        return _number_or_auto(key, value, int, lambda n: n >= 1, "a positive integer")
    except ConfigError:
        raise ConfigError(key, f"expected a positive integer, 'auto' or 'by_views', got {value!r}") from None


def _check_virtual_views(key: str, value):
    """A period in steps (0: off), or "auto" (train/virtual_views.py: every step with few training views)."""
    return _number_or_auto(key, value, int, lambda n: n >= 0, "a step period >= 0")


def _check_drop_rate(key: str, value):
    """A fraction in [0, 1), or "auto" (train/dropout.py: on with few training views)."""
    return _number_or_auto(key, value, float, lambda r: 0.0 <= r < 1.0, "a fraction in [0, 1)")


def _check_unpool_every(key: str, value):
    """A period in refines (0: off), or "auto" (train/unpool.py: on with more than a few training views)."""
    return _number_or_auto(key, value, int, lambda n: n >= 0, "a period in refines >= 0")


def _check_prior_confidence(key: str, value):
    """A confidence in [0, 1], or "auto" (train/lifted_prior.py: by the number of training views)."""
    return _number_or_auto(key, value, float, lambda c: 0.0 <= c <= 1.0, "a confidence in [0, 1]")


def _check_auto_bool(key: str, value):
    """true, false or "auto" (the code picks per device)."""
    if isinstance(value, str) and value.strip().lower() == "auto":
        return "auto"
    try:
        return _as_bool(key, value)
    except ConfigError:
        raise ConfigError(key, f"expected true, false or 'auto', got {value!r}") from None


def _check_device(key: str, value: str) -> None:
    import re

    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", value):
        raise ConfigError(key, f"expected auto, cpu, cuda or cuda:N, got {value!r}")


def _check_background(key: str, value):
    if isinstance(value, str):
        if value == "auto" or value in BACKGROUNDS:
            return value
        raise ConfigError(key, f"expected 'auto', 'black', 'white' or [r, g, b], got {value!r}")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value] * 3
    if isinstance(value, (list, tuple)) and len(value) == 3:
        try:
            rgb = [float(v) for v in value]
        except (TypeError, ValueError):
            rgb = None
        if rgb is not None and all(0.0 <= v <= 1.0 for v in rgb):
            return rgb
    raise ConfigError(key, f"expected 'auto', 'black', 'white' or [r, g, b] in [0, 1], got {value!r}")


def _check_losses(value) -> dict:
    from warpgs.losses.registry import parse_schedule

    if value is None:
        raise ConfigError("losses", "expected a mapping {name: weight}; set a weight to 0 to remove a term")
    if isinstance(value, (list, tuple)):
        value = {name: None for name in value}
    if not isinstance(value, Mapping):
        raise ConfigError("losses", f"expected a mapping {{name: weight}}, got {value!r}")
    out = {}
    for name, spec in value.items():
        key = f"losses.{name}"
        if isinstance(spec, Mapping):
            unknown = set(spec) - {"weight", "schedule"}
            if unknown:
                raise ConfigError(f"{key}.{sorted(unknown)[0]}", "unknown key (a loss takes 'weight' and 'schedule')")
            spec = dict(spec)
            if "weight" in spec:
                spec["weight"] = _check_weight(f"{key}.weight", spec["weight"])
            if spec.get("schedule") is not None:
                try:
                    parse_schedule(spec["schedule"])
                except (ValueError, TypeError) as e:
                    raise ConfigError(f"{key}.schedule", str(e).replace("schedule: ", "")) from None
            out[str(name)] = spec
        elif spec is None or (isinstance(spec, str) and spec.lower() in ("none", "null", "default")):
            out[str(name)] = None  # the registered default weight and schedule
        else:
            out[str(name)] = _check_weight(key, spec)
    return out


def _check_weight(key: str, value) -> float:
    w = _as_number(key, value, float)
    if not math.isfinite(w) or w < 0:
        raise ConfigError(key, f"weight must be finite and >= 0, got {value!r}")
    return w


def _check_imports(value) -> list:
    if value is None:
        return []
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) and v for v in value):
        raise ConfigError("imports", f"expected a list of module names, got {value!r}")
    return list(value)


def _check_extensions(value) -> dict:
    if value is None:
        return {}
    if isinstance(value, (list, tuple)):
        value = {name: {} for name in value}
    if not isinstance(value, Mapping):
        raise ConfigError("extensions", f"expected a mapping {{name: options}}, got {value!r}")
    out = {}
    for name, opts in value.items():
        if opts is not None and not isinstance(opts, Mapping):
            raise ConfigError(f"extensions.{name}", f"expected a mapping of options, got {opts!r}")
        out[str(name)] = dict(opts or {})
    return out


def _check_cross(cfg: Config) -> None:
    if cfg.model.sh_degree < 0 or cfg.model.sh_degree > 3:
        raise ConfigError("model.sh_degree", f"expected 0..3, got {cfg.model.sh_degree}")
    if not 0.0 < cfg.model.init_opacity < 1.0:
        raise ConfigError("model.init_opacity", f"expected a value in (0, 1), got {cfg.model.init_opacity}")
    if cfg.model.background_radius <= 1.0:
        raise ConfigError("model.background_radius", f"expected > 1 (outside the scene), got {cfg.model.background_radius}")
    if not 0.0 < cfg.train.near < cfg.train.far:
        raise ConfigError("train.near", f"need 0 < near < far, got near={cfg.train.near}, far={cfg.train.far}")
    if cfg.train.tile_size is not None and cfg.train.tile_size > 32:
        raise ConfigError("train.tile_size", f"at most 32, got {cfg.train.tile_size}")
    if not 0.0 < cfg.train.surfel_screen_sigma < float("inf"):
        raise ConfigError("train.surfel_screen_sigma", f"expected a positive number of pixels, got "
                          f"{cfg.train.surfel_screen_sigma}")
    for key in ("virtual_rgb", "virtual_depth"):
        if not 0.0 <= getattr(cfg.train, key) < float("inf"):
            raise ConfigError(f"train.{key}", f"expected a weight >= 0, got {getattr(cfg.train, key)}")
    if cfg.train.drop_schedule == "ramp" and cfg.train.steps == "auto":
        raise ConfigError("train.drop_schedule", "'ramp' rises to the rate at the run's last step, which "
                          "train.steps=auto does not know in advance: give a fixed train.steps or use 'constant'")
    if not cfg.train.drop_near >= 0.0:
        raise ConfigError("train.drop_near", f"expected a power >= 0 (0: off), got {cfg.train.drop_near}")
    if not 0.0 <= cfg.train.opacity_decay < 1.0:
        raise ConfigError("train.opacity_decay", f"expected a fraction in [0, 1), got {cfg.train.opacity_decay}")
    if cfg.train.max_sigmas < 0:
        raise ConfigError("train.max_sigmas", f"expected >= 0 (0: exact footprint), got {cfg.train.max_sigmas}")
    problem = alpha_clamp_problem(cfg.train.alpha_min, cfg.train.alpha_max)
    if problem:
        raise ConfigError(f"train.{problem[0]}", problem[1])
    if not LOWEST_TRANSMITTANCE_MIN <= cfg.train.transmittance_min < 1.0:  # see raster_defaults
        raise ConfigError("train.transmittance_min", f"expected a value in [{LOWEST_TRANSMITTANCE_MIN:g}, 1), got "
                          f"{cfg.train.transmittance_min} (smaller ones let the transmittance underflow)")
    # Primitives with opacity below alpha_min never reach a tile, so they get no gradient: a model that starts
    # there, or an opacity reset that puts every primitive there, never renders again.
    if cfg.model.init_opacity <= cfg.train.alpha_min:
        raise ConfigError("train.alpha_min", f"{cfg.train.alpha_min} is not below model.init_opacity "
                          f"({cfg.model.init_opacity}): every primitive would start invisible")
    if cfg.strategy.reset_every > 0 and cfg.strategy.reset_opacity <= cfg.train.alpha_min:
        raise ConfigError("train.alpha_min", f"{cfg.train.alpha_min} is not below strategy.reset_opacity "
                          f"({cfg.strategy.reset_opacity}): every opacity reset would make all primitives invisible "
                          "for good; raise strategy.reset_opacity above it or set strategy.reset_every=0")
    if cfg.data.downscale not in (1, 2, 4, 8):
        raise ConfigError("data.downscale", f"expected 1, 2, 4 or 8, got {cfg.data.downscale}")
    for name, dim in cfg.model.features.items():
        if not name.isidentifier():
            raise ConfigError(f"model.features.{name}", "feature names must be Python identifiers")
        if dim < 1:
            raise ConfigError(f"model.features.{name}", f"expected a positive channel count, got {dim}")
    for name in ("output.ply", "output.checkpoint", "output.metrics"):
        value = getattr(cfg.output, name.split(".")[1])
        if not value or os.sep in value:
            raise ConfigError(name, f"expected a plain file name, got {value!r}")
