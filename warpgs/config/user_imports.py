"""Importing the modules a config lists under `imports:` (module names or .py files), e.g. custom losses."""
from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path


def import_user_module(spec: str):
    """`imports:` entries: a module name (searched on sys.path and in the working directory) or a .py file."""
    if spec.endswith(".py"):
        path = Path(spec)
        if not path.is_file():
            raise ValueError(f"imports: no file {spec!r}")
        name = "warpgs_user_" + path.stem
        if name in sys.modules:
            return sys.modules[name]
        loader_spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(loader_spec)
        sys.modules[name] = module
        try:
            loader_spec.loader.exec_module(module)
        except Exception:
            del sys.modules[name]
            raise
        return module
    try:
        return importlib.import_module(spec)
    except ModuleNotFoundError as e:
        if e.name != spec.split(".")[0] or str(Path.cwd()) in sys.path:
            raise ValueError(f"imports: cannot import {spec!r} ({e})") from None
    sys.path.insert(0, str(Path.cwd()))  # as `python -m` does; console scripts do not
    try:
        return importlib.import_module(spec)
    except ModuleNotFoundError as e:
        raise ValueError(f"imports: cannot import {spec!r} ({e}); give a module on PYTHONPATH or a .py file") from None
