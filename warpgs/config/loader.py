"""Training configuration: YAML files mapped onto nested dataclasses, with `key=value` overrides.

    cfg = load_config("configs/default.yaml", ["steps=500", "model.kind=surfels", "losses.dssim=0"])
    cfg.train.steps -> 500

Sections: data, model, optim (`warpgs.train.optim.OptimConfig`), strategy (`warpgs.train.strategy.StrategyConfig`),
losses ({name: weight} or {name: {weight, schedule}}; weight 0 removes a term), train, eval, output, plus
`imports` (Python modules imported first, e.g. ones that register custom losses) and `extensions`
({name: {options}} of registered trainer extensions, see `warpgs.train.extensions`).

A YAML file may start from another one with `base: other.yaml` (relative to the file); mappings merge key by
key. Overrides use dotted paths (`optim.means_lr=1e-4`) or the short aliases in `ALIASES` (`steps=N`,
`device=cpu`, `eval_every=N`, `seed=N`, ...); values are parsed as YAML and then checked against the field's
type. Every mistake raises `ConfigError` naming the key, with close matches for misspelt keys.
"""
from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Mapping, Sequence, Union

import yaml

from warpgs.config.checks import from_dict
# The schema is re-exported: `from warpgs.config import Config, TrainConfig, ConfigError, ...` works.
from warpgs.config.schema import (ALIASES, BACKGROUNDS, CHOICES, FREE_MAPPINGS, NON_NEGATIVE,  # noqa: F401
                                  POSITIVE, SECTIONS, Config, ConfigError, DataConfig, EvalConfig, ModelConfig,
                                  OptimConfig, OutputConfig, StrategyConfig, TrainConfig, all_keys)


# ----- public entry points ----------------------------------------------------------------------------------
def load_config(source: Union[None, str, os.PathLike, Mapping, Config] = None,
                overrides: Sequence[str] = ()) -> Config:
    """YAML path / mapping / Config (None: the defaults) plus `key=value` overrides -> a checked Config."""
    if isinstance(source, Config):
        raw = source.to_dict()
    elif source is None:
        raw = {}
    elif isinstance(source, Mapping):
        raw = copy.deepcopy(dict(source))
    else:
        raw = read_yaml(source)
    # Everything merges onto the defaults (losses too: a term is removed by giving it weight 0).
    raw = deep_merge(Config().to_dict(), raw) if isinstance(raw, Mapping) else raw
    for item in overrides:
        key, value = parse_override(item)
        set_path(raw, key, value)
    return from_dict(raw)


def read_yaml(path, _seen: tuple = ()) -> dict:
    """A YAML config as a dict, with `base:` files merged underneath."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError("", f"config file {path} not found")
    if path.resolve() in _seen:
        raise ConfigError("base", f"{path} includes itself (base chain {[str(p) for p in _seen]})")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError("", f"{path}: not valid YAML ({e})") from None
    if not isinstance(data, dict):
        raise ConfigError("", f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ConfigError("base", f"expected a file name, got {base!r}")
    return deep_merge(read_yaml(path.parent / base, _seen + (path.resolve(),)), data)


def parse_key_value(item: str) -> tuple:
    """'key=value' -> ('key', the value read as YAML, else the text); no alias expansion."""
    if not isinstance(item, str) or "=" not in item:
        raise ConfigError(str(item), "overrides look like key=value (e.g. steps=500, model.kind=surfels)")
    key, text = item.split("=", 1)
    key = key.strip()
    if not key:
        raise ConfigError("", f"override {item!r} has no key")
    try:
        value = yaml.safe_load(text) if text.strip() else None
    except yaml.YAMLError:
        value = text
    return key, value


def parse_override(item: str) -> tuple:
    """'a.b=value' -> ('a.b', parsed value); the key's alias is expanded."""
    key, value = parse_key_value(item)
    head, _, rest = key.partition(".")
    if head in ALIASES and not rest:
        key = ALIASES[head]
    return key, value


def set_path(raw: dict, key: str, value) -> None:
    parts = key.split(".")
    node = raw
    for p in parts[:-1]:
        nxt = node.get(p)
        if not isinstance(nxt, dict):
            nxt = {}
            node[p] = nxt
        node = nxt
    node[parts[-1]] = value


def deep_merge(base: dict, top: Mapping) -> dict:
    out = copy.deepcopy(base)
    for k, v in top.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out
