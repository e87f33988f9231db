"""warpgs: differentiable Gaussian splatting with NVIDIA Warp kernels (CUDA and CPU).

Names are imported on first use, so `import warpgs.losses` (or warpgs.data) does not load Warp.
"""
import importlib

_LAZY = {
    "rasterize": "warpgs.render.gaussians", "RenderOutput": "warpgs.render.gaussians", "rasterize_surfels": "warpgs.render.surfels",
    "register_loss": "warpgs.losses", "Trainer": "warpgs.train.trainer",
    "load_config": "warpgs.config.loader",
}

__all__ = list(_LAZY)
__version__ = "0.1.0"


def __getattr__(name):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'warpgs' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
