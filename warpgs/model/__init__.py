"""The model: 3D Gaussian and 2D surfel parameter sets (init, densify/prune maths), PLY files, the learned
environment map, and rendering a model through the render op."""
from warpgs._lazy import lazy_exports

_NAMES = {
    "GaussianModel": "warpgs.model.gaussians",
    "render_model": "warpgs.model.rendering",
}
__all__ = list(_NAMES)
__getattr__, __dir__ = lazy_exports(globals(), _NAMES)
