"""warpgs: differentiable Gaussian splatting with NVIDIA Warp kernels (CUDA and CPU)."""
from warpgs.render import RenderOutput, rasterize
from warpgs.render_surfels import rasterize_surfels

__all__ = ["rasterize", "rasterize_surfels", "RenderOutput"]
__version__ = "0.1.0"
