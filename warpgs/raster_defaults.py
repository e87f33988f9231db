"""Default renderer settings, shared by the render ops, the Warp pipelines and the trainer's config (no Warp or
torch import here, so the config stays light). Thresholds are the 3DGS rules; the tile size is the fastest exact
setting measured by benchmarks/speed_vs_error.py and benchmarks/raster.py --tile-sizes on a GPU and on the CPU."""
DEFAULT_TILE_SIZE = 8
DEFAULT_ALPHA_MIN = 1.0 / 255.0  # contributions below this alpha are skipped
DEFAULT_TRANSMITTANCE_MIN = 1.0e-4  # a pixel stops blending before its transmittance drops under this
# The adjoint recovers each Gaussian's transmittance from the final one by division, so the final one must stay a
# normal float32: a smaller transmittance_min (0 included) would let it underflow and corrupt the gradients.
LOWEST_TRANSMITTANCE_MIN = 1.0e-30
