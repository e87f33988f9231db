"""Training configuration: YAML files mapped onto nested dataclasses, with `key=value` overrides.

    cfg = load_config("configs/default.yaml", ["steps=500", "model.kind=surfels", "losses.dssim=0"])
    cfg.train.steps -> 500

Sections: data, model, optim (`warpgs.optim.OptimConfig`), strategy (`warpgs.strategy.StrategyConfig`),
losses ({name: weight} or {name: {weight, schedule}}; weight 0 removes a term), train, eval, output, plus
`imports` (Python modules imported first, e.g. ones that register custom losses) and `extensions`
({name: {options}} of registered trainer extensions, see `warpgs.extensions`).

A YAML file may start from another one with `base: other.yaml` (relative to the file); mappings merge key by
key. Overrides use dotted paths (`optim.means_lr=1e-4`) or the short aliases in `ALIASES` (`steps=N`,
`device=cpu`, `eval_every=N`, `seed=N`, ...); values are parsed as YAML and then checked against the field's
type. Every mistake raises `ConfigError` naming the key, with close matches for misspelt keys.
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import math
import os
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union

import yaml

from warpgs.optim import OptimConfig
from warpgs.strategy import StrategyConfig


class ConfigError(ValueError):
    """A bad config key or value; `key` is the dotted path at fault."""

    def __init__(self, key: str, problem: str):
        self.key = key
        super().__init__(f"{key}: {problem}" if key else problem)


@dataclass
class DataConfig:
    path: Optional[str] = None  # scene folder (COLMAP, transforms.json, light field); None: built-in synthetic
    synthetic: str = "orbit"  # built-in scene when path is None: "orbit" (dense ring) or "lightfield" (3x3)
    width: int = 128  # built-in scene resolution
    height: int = 96
    split: Optional[str] = None  # None: split.json when present else all train (light fields: "grid"); "llff", "all"
    n_train: Optional[int] = None  # keep this many training views (evenly spread)
    downscale: int = 1  # serve images at 1/downscale (1, 2, 4, 8)
    depth_priors: Optional[str] = "auto"  # "auto": the scene's prior files if any; "none"; or a folder of priors
    preload: bool = True  # keep all training views on the device


@dataclass
class ModelConfig:
    kind: str = "gaussians"  # "gaussians" (3DGS) or "surfels" (2DGS)
    sh_degree: int = 3  # highest SH degree
    sh_interval: int = 1000  # raise the active SH degree by one every this many steps (0: all bands from the start)
    init: str = "auto"  # "auto" (SfM points, else depth priors, else random), "sfm", "depth", "random"
    init_points: int = 100_000  # points drawn for depth/random initialisation
    init_opacity: float = 0.1
    background_points: int = 0  # extra points on a far sphere, where sky/background can live (0: none, as 3DGS)
    background_radius: float = 3.0  # that sphere's radius, in multiples of the scene's radius
    init_knn: int = 3  # initial scale: RMS distance to this many nearest points
    features: Dict[str, int] = field(default_factory=dict)  # extra per-primitive params rendered as `features`


@dataclass
class TrainConfig:
    steps: int = 30_000
    seed: int = 0
    device: str = "auto"  # "auto" (CUDA when available), "cpu", "cuda", "cuda:N"
    background: Any = "auto"  # "auto" (the scene's, else black), "black", "white" or [r, g, b] in [0, 1]
    near: float = 0.01
    far: float = 1e10
    tile_size: int = 16
    # Accuracy knobs of the renderer (defaults: the 3DGS rules, exact within them); raising them trades
    # accuracy for speed, see benchmarks/speed_vs_error.py.
    max_sigmas: float = 0.0  # > 0: truncate each footprint at this many sigmas
    alpha_min: float = 1.0 / 255.0  # skip contributions below this alpha
    transmittance_min: float = 1.0e-4  # stop blending a pixel before its transmittance drops under this
    scene_extent: Optional[float] = None  # None: from the cameras (3DGS); scales means_lr and densify sizes
    checkpoint_every: int = 1000  # 0: only at the end (and on Ctrl-C)
    log_every: int = 100  # progress line period when the output is not a terminal
    progress: bool = True
    nan_guard: bool = True  # stop at the first non-finite loss, gradient or parameter
    threads: int = 0  # torch CPU threads during fit (0: 1 on CPU, where Warp's own thread pool uses the cores;
    #                   torch's default on CUDA)

    def render_options(self) -> dict:
        """The renderer settings every render of the model uses (training, evaluation, queries)."""
        return dict(near=self.near, far=self.far, tile_size=self.tile_size, max_sigmas=self.max_sigmas,
                    alpha_min=self.alpha_min, transmittance_min=self.transmittance_min)


@dataclass
class EvalConfig:
    every: int = 1000  # evaluate the held-out views every this many steps (0: only at the end)
    split: str = "test"  # "test" or "train" (the final metrics fall back to train when there is no test split)
    lpips: bool = True  # LPIPS when its weights are on disk (never downloaded)
    lpips_net: str = "alex"
    save_images: bool = True  # write the final test renders as PNG
    max_views: int = 0  # evaluate at most this many views during training (0: all); the final pass uses all


@dataclass
class OutputConfig:
    dir: Optional[str] = None  # None: outputs/<scene name>
    ply: str = "point_cloud.ply"
    checkpoint: str = "checkpoint.pt"
    metrics: str = "metrics.json"


@dataclass
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    strategy: StrategyConfig = field(default_factory=StrategyConfig)
    losses: Dict[str, Any] = field(default_factory=lambda: {"l1": 0.8, "dssim": 0.2})
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    imports: List[str] = field(default_factory=list)
    extensions: Dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return _plain(dataclasses.asdict(self))

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=False)

    def copy(self) -> "Config":
        return copy.deepcopy(self)


ALIASES = {
    "steps": "train.steps", "device": "train.device", "eval_every": "eval.every", "seed": "train.seed",
    "background": "train.background", "out": "output.dir", "data": "data.path", "kind": "model.kind",
    "budget": "strategy.max_primitives", "max_primitives": "strategy.max_primitives",
    "sh_degree": "model.sh_degree", "checkpoint_every": "train.checkpoint_every",
}
CHOICES = {
    "data.synthetic": ("orbit", "lightfield"),
    "data.split": ("file", "llff", "all", "grid"),  # "grid": light-field folders (their default)
    "model.kind": ("gaussians", "surfels"),
    "model.init": ("auto", "sfm", "depth", "random"),
    "eval.split": ("test", "train"),
    "eval.lpips_net": ("alex", "vgg", "squeeze"),
}
POSITIVE = {"data.width", "data.height", "data.downscale", "data.n_train", "model.init_points", "model.init_knn",
            "train.steps", "train.tile_size"}
NON_NEGATIVE = {"model.sh_interval", "model.background_points", "train.checkpoint_every", "train.log_every", "train.threads", "eval.every",
                "eval.max_views"}
# Mappings whose keys are free (user names), not fields.
FREE_MAPPINGS = {"losses", "extensions", "model.features", "optim.extras_lr"}
SECTIONS = {f.name: f for f in dataclasses.fields(Config)}


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


def parse_override(item: str) -> tuple:
    """'a.b=value' -> ('a.b', parsed value); the key's alias is expanded."""
    if not isinstance(item, str) or "=" not in item:
        raise ConfigError(str(item), "overrides look like key=value (e.g. steps=500, model.kind=surfels)")
    key, text = item.split("=", 1)
    key = key.strip()
    if not key:
        raise ConfigError("", f"override {item!r} has no key")
    head, _, rest = key.partition(".")
    if head in ALIASES and not rest:
        key = ALIASES[head]
    try:
        value = yaml.safe_load(text) if text.strip() else None
    except yaml.YAMLError:
        value = text
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


def all_keys() -> List[str]:
    """Every dotted key a config accepts (free mappings appear as their own key)."""
    keys = []
    for name, f in SECTIONS.items():
        default = f.default_factory()
        if dataclasses.is_dataclass(default):
            keys += [f"{name}.{g.name}" for g in dataclasses.fields(default)]
        else:
            keys.append(name)
    return keys + list(ALIASES)


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


def _type_name(tp) -> str:
    return getattr(tp, "__name__", str(tp).replace("typing.", ""))


def _check_value(key: str, value, tp):
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
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
        if not isinstance(value, (list, tuple)):
            raise ConfigError(key, f"expected a list, got {value!r}")
        return list(value)
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "yes", "on", "1", "false", "no", "off", "0"):
            return value.lower() in ("true", "yes", "on", "1")
        if isinstance(value, int) and value in (0, 1):
            return bool(value)
        raise ConfigError(key, f"expected true or false, got {value!r}")
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


def _check_device(key: str, value: str) -> None:
    import re

    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", value):
        raise ConfigError(key, f"expected auto, cpu, cuda or cuda:N, got {value!r}")


BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}


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
    if cfg.train.tile_size > 32:
        raise ConfigError("train.tile_size", f"at most 32, got {cfg.train.tile_size}")
    if cfg.train.max_sigmas < 0:
        raise ConfigError("train.max_sigmas", f"expected >= 0 (0: exact footprint), got {cfg.train.max_sigmas}")
    if not 0.0 < cfg.train.alpha_min < 0.99:
        raise ConfigError("train.alpha_min", f"expected a value in (0, 0.99), got {cfg.train.alpha_min}")
    if not 0.0 <= cfg.train.transmittance_min < 1.0:
        raise ConfigError("train.transmittance_min", f"expected a value in [0, 1), got {cfg.train.transmittance_min}")
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


def _plain(obj):
    """Tuples -> lists so the YAML dump stays plain."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj
