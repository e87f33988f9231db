"""Configuration: YAML presets and key=value overrides mapped onto checked dataclasses (schema.py), with
errors that name the key (checks.py); `imports:` modules a config lists (user_imports.py)."""
from warpgs.config.loader import deep_merge, load_config, parse_override, read_yaml, set_path  # noqa: F401
from warpgs.config.schema import (ALIASES, BACKGROUNDS, CHOICES, FREE_MAPPINGS, NON_NEGATIVE,  # noqa: F401
                                  POSITIVE, SECTIONS, Config, ConfigError, DataConfig, EvalConfig, ModelConfig,
                                  OptimConfig, OutputConfig, StrategyConfig, TrainConfig, all_keys)

__all__ = ["load_config", "Config", "ConfigError", "DataConfig", "EvalConfig", "ModelConfig", "OptimConfig",
           "OutputConfig", "StrategyConfig", "TrainConfig", "read_yaml", "parse_override", "set_path", "deep_merge"]
