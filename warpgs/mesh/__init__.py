"""Meshes from trained models: sparse TSDF fusion of rendered depth (Warp kernels in kernels/tsdf*.py),
marching cubes, clean-up and binary PLY output; `warpgs-mesh` is cli.py."""
from warpgs.mesh.volume import Bound, Mesh, SparseTSDFVolume

__all__ = ["Bound", "Mesh", "SparseTSDFVolume"]
