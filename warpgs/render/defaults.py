"""Default renderer settings, shared by the render ops, the Warp pipelines and the trainer's config (no Warp or
torch import here, so the config stays light). Thresholds are the 3DGS rules. Tile sizes change speed only (the
image does not depend on them); the defaults are the fastest measured by benchmarks/raster.py --tile-sizes 8,16
on H100/H200 GPUs and on the CPU: 8 on the CPU (up to 2x faster than 16, forward and backward) and on GPUs when a
backward pass follows (fwd+bwd faster at 100k, 300k and 1M Gaussians); for forward-only GPU renders of 3D Gaussians
8 while they are sparse (13% faster at 100k Gaussians at 1080p) and 16 once they are dense (6% faster at 300k, 20% at
1M, where sorting 2-2.5x more tile keys costs); surfels take 8 for every render (their forward at 8 is 10-25% faster
than at 16 at 100k, 300k and 1M: raster_cuda_h200_surfels_tiles_s28.json)."""
import os
from contextlib import contextmanager
from dataclasses import dataclass, fields, replace

DEFAULT_TILE_SIZE = 8  # the CPU, and GPU renders that will be differentiated (training)
GPU_FORWARD_ONLY_TILE_SIZE = 16  # dense GPU renders of 3D Gaussians nobody differentiates (evaluation, viewers)
# 3D Gaussians per pixel of the image from which forward-only GPU renders take 16: between the measured sides of the
# crossover at 1080p (100k Gaussians = 0.05 a pixel: 8 faster; 300k = 0.14: 16 faster; raster_cuda_h200_tiles_s27.json).
DENSE_PRIMITIVES_PER_PIXEL = 0.1
DEFAULT_ALPHA_MIN = 1.0 / 255.0  # contributions below this alpha are skipped
DEFAULT_ALPHA_MAX = 0.99  # alpha is clamped here (3DGS; gsplat uses 0.999)
DEFAULT_TRANSMITTANCE_MIN = 1.0e-4  # a pixel stops blending before its transmittance drops under this
# Surfels: the screen-space fallback's standard deviation in pixels of the image rendered (2DGS: 1/sqrt(2)). Scaled
# with the image by the model renders (warpgs/model/rendering.py surfel_screen_sigma): fixed in pixels, it dilates
# every surfel seen from farther or at a lower resolution than training saw it.
DEFAULT_SURFEL_SCREEN_SIGMA = 0.5 ** 0.5
# 3D Gaussians: the low-pass (px²) added to every projected covariance (3DGS; gsplat's eps2d), scaled the same way by
# the model renders (surfel_screen_sigma's twin, warpgs/model/rendering.py gaussian_low_pass).
DEFAULT_LOW_PASS = 0.3
# The adjoint recovers each Gaussian's transmittance from the final one by division, so the final one must stay a
# normal float32: a smaller transmittance_min (0 included) would let it underflow and corrupt the gradients.
LOWEST_TRANSMITTANCE_MIN = 1.0e-30
DEPTH_EPS = 1e-10  # expected depth = accumulated depth / max(alpha, DEPTH_EPS)


# The adjoint divides by 1 - alpha to recover each transmittance: a clamp closer to 1 would lose float32 precision.
HIGHEST_ALPHA_MAX = 0.9999


def alpha_clamp_problem(alpha_min: float, alpha_max: float):
    """(argument, what is wrong) for a blend's alpha_min and alpha_max, or None when they are usable."""
    if not 0.0 < alpha_max <= HIGHEST_ALPHA_MAX:
        return "alpha_max", (f"expected a value in (0, {HIGHEST_ALPHA_MAX}], got {alpha_max} (the adjoint divides by "
                             f"1 - alpha)")
    if not 0.0 < alpha_min < alpha_max:  # alpha never exceeds alpha_max, so a larger threshold would drop everything
        return "alpha_min", f"expected a value in (0, alpha_max = {alpha_max}), got {alpha_min}"
    return None


def choose_tile_size(tile_size, needs_grad: bool, on_gpu: bool, primitives_per_pixel=None, surfels: bool = False) -> int:
    """tile_size as given, or (None) the measured default for this device and kind of render. 3D Gaussians:
    primitives_per_pixel (their count over the image's pixels) keeps sparse forward-only GPU renders at 8 (None: taken
    as dense). Surfels: 8 always."""
    if tile_size is not None:
        return tile_size
    if not on_gpu or needs_grad or surfels:
        return DEFAULT_TILE_SIZE
    if primitives_per_pixel is not None and primitives_per_pixel < DENSE_PRIMITIVES_PER_PIXEL:
        return DEFAULT_TILE_SIZE
    return GPU_FORWARD_ONLY_TILE_SIZE


# Which GPU blend adjoint the ops launch (speed only: both give the same images and gradients, which the tests
# check). Benchmarks switch them in one process with `raster_options(...)`; the WARPGS_* variables set the defaults.
# GPU blend adjoint of 3D Gaussians: blend_gpu.backward_kernel_warp_sums with each Gaussian's ten gradient sums made
# by one reduce-scatter and written from ten lanes ("scatter", the default: the adjoint kernel 5% faster at 100k and
# 1M Gaussians at 1080p on an H200, render_trace_cuda_scatter_s35.json; fwd+bwd 1-7% faster,
# raster_cuda_h200_scatter{2,3}_s35.json) or ten butterfly sums written by lane 0 ("warp_sums"; the same gradients up
# to float32 rounding), or backward_kernel ("block").
BACKWARD_KERNELS = ("warp_sums", "scatter", "block")
# Surfels: the same three; "scatter" (a 32-value reduce-scatter, the default) took fwd+bwd 10% faster at 100k and 5% at
# 1M surfels at 1080p on an H200 against lane 0's sums, gradients equal up to float32 rounding
# (raster_cuda_h200_surfels_scatter_s36.json).
SURFEL_BACKWARD_KERNELS = ("warp_sums", "scatter", "block")
PER_WARP_ADJOINTS = ("warp_sums", "scatter")  # the variants that run a backward_kernel_warp_sums (both kinds)
# How a GPU thread of the tile-key emission finds its primitive: "table" (kernels/binning.py emit_tile_keys_by_table,
# its binary search narrowed by a coarse table) or "full" (emit_tile_keys_per_pair, a search over every primitive).
# The 3D projection's adjoint: "written" (kernels/project_adjoint.py, for one camera that is not differentiated; the
# generated one serves the rest) or "generated" (Warp's, of kernels/project.py). Together the first of each took
# 1M-Gaussian 1080p forward+backward calls 6-7% faster on an H200 and left 100k and 300k within noise
# (raster_cuda_h200_keys_padj_run{1,2,3}_s28.json).
PAIR_SEARCHES = ("table", "full")
# The tile-pair sort of a GPU render that reads its pair count ("table" search): "padded" sorts a room of the count
# rounded up to a sixteenth of its leading power of two, sentinels past the pairs (tile_binning.padded_capacity), so
# renders of nearby views launch the same sequence and it replays as one CUDA graph; "exact" sorts the count itself
# with its launches issued one by one. "ahead": as "padded" for a render's first at its kind and size, for
# deterministic ones and where the room is over twice the last count; the others sort into a room sized from earlier
# renders before their count is read, and check the count while the GPU blends (sort_ahead.AheadSort; a render whose
# pairs did not fit is sorted and blended again): the GPU does not wait for the host between the count and the blend.
# Same pairs in the same order (tests/test_binning.py, tests/test_sort_ahead.py).
PAIR_SORTS = ("ahead", "padded", "exact")
PROJECT_ADJOINTS = ("written", "generated")


@dataclass(frozen=True)
class RasterOptions:
    backward_kernel: str = os.environ.get("WARPGS_BWD_KERNEL", "scatter")
    # Surfels: the per-warp adjoint halves fwd+bwd on an H200 (raster_cuda_h200_surfels_*.json); "block" is the old one.
    surfel_backward_kernel: str = os.environ.get("WARPGS_SURFEL_BWD_KERNEL", "scatter")
    # GPU gradients bit-identical from run to run: the blend adjoint sums each primitive's per-tile parts in a fixed
    # order instead of with float atomics (render/pair_adjoint.py). Off: faster. The CPU is deterministic either way.
    deterministic: bool = os.environ.get("WARPGS_DETERMINISTIC", "0") == "1"
    pair_search: str = os.environ.get("WARPGS_PAIR_SEARCH", "table")  # both give the same keys (tests/test_binning.py)
    project_adjoint: str = os.environ.get("WARPGS_PROJECT_ADJOINT", "written")  # tests/test_project_adjoint.py
    pair_sort: str = os.environ.get("WARPGS_PAIR_SORT", "ahead")
    # GPU renders size their tile-pair sort from earlier calls' counts instead of waiting for their own
    # (render/pair_room.py); a render that did not fit says so in out.pairs_overflowed. Set per call (rasterize,
    # rasterize_surfels).
    speculative_pairs: bool = False

    def __post_init__(self):
        for f, allowed in (("backward_kernel", BACKWARD_KERNELS), ("surfel_backward_kernel", SURFEL_BACKWARD_KERNELS)):
            if getattr(self, f) not in allowed:
                raise ValueError(f"raster option {f}: expected one of {allowed}, got {getattr(self, f)!r}")
        if self.project_adjoint not in PROJECT_ADJOINTS:
            raise ValueError(f"raster option project_adjoint: expected one of {PROJECT_ADJOINTS}, got "
                             f"{self.project_adjoint!r}")
        for f, allowed in (("pair_search", PAIR_SEARCHES), ("pair_sort", PAIR_SORTS)):
            if getattr(self, f) not in allowed:
                raise ValueError(f"raster option {f}: expected one of {allowed}, got {getattr(self, f)!r}")
        for f in ("deterministic", "speculative_pairs"):
            if not isinstance(getattr(self, f), bool):
                raise ValueError(f"raster option {f}: expected True or False, got {getattr(self, f)!r}")


_options = [RasterOptions()]


def current_raster_options() -> RasterOptions:
    return _options[-1]


@contextmanager
def raster_options(**changes):
    """Within the block, renders use these options (e.g. raster_options(backward_kernel="block")). One stack for
    the process: meant for benchmarks and tests, not for threads that render concurrently."""
    unknown = sorted(set(changes) - {f.name for f in fields(RasterOptions)})
    if unknown:
        raise ValueError(f"raster_options: unknown option(s) {unknown}; expected some of "
                         f"{[f.name for f in fields(RasterOptions)]}")
    _options.append(replace(_options[-1], **changes))
    try:
        yield _options[-1]
    finally:
        _options.pop()


def options_for_call(deterministic=None, speculative_pairs: bool = False) -> RasterOptions:
    """The raster options one render uses: the current ones, with a render's own `deterministic` (None: keep) and
    `speculative_pairs`."""
    options = current_raster_options()
    changes = {}
    if deterministic is not None and deterministic != options.deterministic:
        changes["deterministic"] = deterministic
    if speculative_pairs != options.speculative_pairs:
        changes["speculative_pairs"] = speculative_pairs
    if not changes:
        return options
    key = (options, tuple(sorted(changes.items())))
    made = _CALL_OPTIONS.get(key)
    if made is None:  # a training loop asks for the same few every step: made once (replace validates anew)
        if len(_CALL_OPTIONS) > 32:
            _CALL_OPTIONS.clear()
        made = _CALL_OPTIONS[key] = replace(options, **changes)
    return made


_CALL_OPTIONS: dict = {}
