"""warpgs: differentiable Gaussian splatting with NVIDIA Warp kernels (CUDA and CPU)."""
from warpgs.render import RenderOutput, rasterize

__all__ = ["rasterize", "RenderOutput"]
__version__ = "0.1.0"
