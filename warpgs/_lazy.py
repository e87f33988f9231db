"""Package-level names imported on first use, so importing a light subpackage (config, losses, data) does
not load Warp through a parent package's __init__."""
from __future__ import annotations

import importlib


def lazy_exports(package_globals: dict, names: dict):
    """Returns (__getattr__, __dir__) for a package whose `names` map a public name to the module defining it."""

    def __getattr__(name):
        if name in names:
            value = getattr(importlib.import_module(names[name]), name)
            package_globals[name] = value
            return value
        raise AttributeError(f"module {package_globals['__name__']!r} has no attribute {name!r}")

    def __dir__():
        return sorted(set(package_globals) | set(names))

    return __getattr__, __dir__
