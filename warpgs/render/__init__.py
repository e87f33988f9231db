"""The render ops (`rasterize` for 3D Gaussians, `rasterize_surfels` for 2D surfels), their launch pipelines
(project -> bin -> sort -> blend, forward and adjoint), default settings and input checks. The only bridge
between torch and the Warp kernels in `warpgs.kernels`."""
from warpgs._lazy import lazy_exports

_NAMES = {
    "rasterize": "warpgs.render.gaussians",
    "RenderOutput": "warpgs.render.gaussians",
    "rasterize_surfels": "warpgs.render.surfels",
}
__all__ = list(_NAMES)
__getattr__, __dir__ = lazy_exports(globals(), _NAMES)
