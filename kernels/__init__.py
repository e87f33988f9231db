"""Warp kernels of warpgs, shipped as ``warpgs.kernels``.

Warp only: nothing here imports torch. One module per pipeline stage; the torch-facing op in
``warpgs.render.gaussians`` launches them.
"""
