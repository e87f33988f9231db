"""The config schema: section dataclasses with their defaults, and the key tables (aliases, choices, ranges)."""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Union

import yaml

from warpgs.train.optim import OptimConfig
from warpgs.render.defaults import (DEFAULT_ALPHA_MAX, DEFAULT_ALPHA_MIN, DEFAULT_SURFEL_SCREEN_SIGMA,
                                    DEFAULT_TRANSMITTANCE_MIN)
from warpgs.train.schedule import ScheduleConfig
from warpgs.train.strategy import StrategyConfig


class ConfigError(ValueError):
    """A bad config key or value; `key` is the dotted path at fault."""

    def __init__(self, key: str, problem: str):
        self.key = key
        super().__init__(f"{key}: {problem}" if key else problem)


@dataclass
class DataConfig:
    path: Optional[str] = None  # scene folder (COLMAP, transforms.json, light field); None: built-in synthetic
    synthetic: str = "orbit"  # built-in scene when path is None: "orbit" (dense ring) or "lightfield" (3x3)
    width: int = 128  # built-in scene resolution
    height: int = 96
    split: Optional[str] = None  # None: split.json when present else all train (light fields: "grid"); "llff", "all"
    n_train: Optional[int] = None  # keep this many training views (evenly spread)
    downscale: int = 1  # serve images at 1/downscale (1, 2, 4, 8)
    depth_priors: Optional[str] = "auto"  # "auto": the scene's prior files if any, else estimated when the config
    #                                       reads priors (train/setup.py what_reads_priors); "none"; "estimate":
    #                                       plane-sweep stereo aligned to the SfM points, written to
    #                                       <output>/depth_priors; or a folder of priors
    depth_prior_options: Dict[str, Any] = field(default_factory=dict)  # with "estimate": PlaneSweepStereo's keyword
    #                                arguments, e.g. {window: 7, num_planes: 192} (warpgs/data/depth/plane_sweep.py)
    depth_prior_fill: float = 0.0  # with "estimate": fill the pixels the stereo left invalid (edge-aware, from the
    #                                valid ones) and give them this confidence in the depth terms; 0: leave them out
    preload: bool = True  # keep all training views on the device (loaded before the first step)
    exclude: List[str] = field(default_factory=list)  # image names, globs or ranges ("0014.jpg", "001[4-9].jpg",
    #                     "0000.jpg..0013.jpg") left out of training and evaluation (e.g. frames SfM posed wrongly);
    #                     the split is otherwise kept (warpgs/data/exclude.py)


@dataclass
class ModelConfig:
    kind: str = "gaussians"  # "gaussians" (3DGS) or "surfels" (2DGS)
    sh_degree: int = 3  # highest SH degree
    sh_interval: int = 1000  # raise the active SH degree by one every this many steps (0: all bands from the start)
    init: str = "auto"  # "auto" (SfM points, else depth priors, else triangulated from the known poses, else
    #                     random), "sfm", "depth", "triangulate", "random"
    init_points: int = 100_000  # points drawn for depth/random initialisation
    prior_points: int = 0  # extra initial points lifted from the depth priors' pixels of the training views, added
    #                         to what model.init gave (few views: triangulation finds few points; 0: none)
    prior_points_confidence: Union[float, str] = 0.5  # ... from pixels whose prior confidence is at least this;
    #                         "auto": 0.8 with few training views, 0.5 with more (train/lifted_prior.py)
    init_opacity: float = 0.1
    background_points: int = 0  # extra points on a far sphere, where sky/background can live (0: none, as 3DGS)
    background_radius: float = 3.0  # that sphere's radius, in multiples of the scene's radius
    init_knn: int = 3  # initial scale: RMS distance to this many nearest points
    features: Dict[str, int] = field(default_factory=dict)  # extra per-primitive params rendered as `features`


@dataclass
class TrainConfig:
    # or "auto": stop by a validation split of the training views (`schedule`); or "by_views": 1000 steps with at most
    # 9 training views, above that 1000 for every three views up to 10000 (train/steps_by_views.py)
    steps: Union[int, str] = 30_000
    seed: int = 0
    device: str = "auto"  # "auto" (CUDA when available), "cpu", "cuda", "cuda:N"
    background: Any = "auto"  # "auto" (the scene's, else black), "black", "white" or [r, g, b] in [0, 1]
    near: float = 0.01
    far: float = 1e10
    tile_size: Optional[int] = None  # speed only (the image does not depend on it); None: 8, or 16 for forward-only
    #                                  GPU renders of dense 3D Gaussians (render/defaults.py choose_tile_size)
    # Accuracy knobs of the renderer (defaults: the 3DGS rules, exact within them); raising them trades
    # accuracy for speed, see benchmarks/speed_vs_error.py.
    max_sigmas: float = 0.0  # > 0: truncate each footprint at this many sigmas
    alpha_min: float = DEFAULT_ALPHA_MIN  # skip contributions below this alpha
    transmittance_min: float = DEFAULT_TRANSMITTANCE_MIN  # stop blending a pixel before its transmittance drops under this
    alpha_max: float = DEFAULT_ALPHA_MAX  # each contribution's alpha clamp: 3DGS's 0.99, gsplat's 0.999 (not for speed)
    # Surfels: the screen-space fallback's sigma in pixels of a training image (2DGS: 1/sqrt(2)), scaled with every
    # other image. Narrower, trained surfels sit nearer curved surfaces (a lone sphere's mesh 0.030 -> 0.014 inside
    # at 0.1) but images can lose PSNR (docs/mesh.md, "One sphere alone").
    surfel_screen_sigma: float = DEFAULT_SURFEL_SCREEN_SIGMA
    scene_extent: Optional[float] = None  # None: from the cameras (3DGS); scales means_lr and densify sizes
    checkpoint_every: int = 1000  # 0: only at the end (and on Ctrl-C)
    log_every: int = 100  # progress line period when the output is not a terminal
    log: str = "jsonl"  # <out>/log.jsonl every log_every steps; "tensorboard": also <out>/tensorboard; "none"
    progress: bool = True
    nan_guard: bool = True  # stop at the first non-finite loss, gradient or parameter
    threads: int = 0  # torch CPU threads during fit (0: 1 on CPU, where Warp's own thread pool uses the cores;
    #                   torch's default on CUDA)
    # Views per optimizer step, over all ranks of a distributed run (each renders its share); the loss is their
    # mean. The schedule stays in steps: divide steps and refine_* by B to see as many views (docs/distributed.md).
    batch_size: int = 1
    batch_scaling: str = "sqrt"  # Adam for the batch: "sqrt" (lr x sqrt(B), eps / sqrt(B), betas as gsplat) or "none"
    dist_backend: str = "auto"  # under torchrun: "auto" (nccl on CUDA, gloo on the CPU), "nccl" or "gloo"
    dist_timeout: int = 900  # seconds a rank waits in a collective before it stops with an error
    # Under torchrun: "data" (every rank holds the whole model and renders its share of the views; gradients are
    # all-reduced) or "model" (3D Gaussians: each rank owns a share of the primitives and renders one view of each
    # round from everybody's, through a splat exchange; docs/distributed.md, "Model parallelism").
    parallel: str = "data"
    viewer: bool = False  # serve a browser viewer of the model as it trains (pip install 'warpgs[viewer]')
    viewer_port: int = 8080  # its port on 127.0.0.1 (0: any free one)
    # Run-to-run identical gradients on GPUs: fixed-order sums in the blend adjoint (rasterize(deterministic=True))
    # and torch.use_deterministic_algorithms; slower (docs/distributed.md, "Deterministic training").
    deterministic: bool = False
    # Time each phase of the step (views, render + backward, all-reduce, optimizer, densify), the device synchronised
    # at each boundary: metrics.json["phases"] per rank; slows the steps a little (train/phase_timer.py).
    profile_phases: bool = False
    # The D-SSIM loss through Warp kernels (render/ssim_op.py) instead of torch's filtering, both replayed from CUDA
    # graphs on a GPU. "auto": Warp on CUDA (an H200 loss forward + backward: 0.74 against 5.2 ms at 1080p, 0.53
    # against 1.00 at 800x534), torch on the CPU (where one Warp launch uses one core and torch's filters all).
    fused_ssim: Union[bool, str] = "auto"
    # GPU training (3D Gaussians and surfels): each render sizes its tile-pair sort from the earlier renders' counts
    # instead of waiting for its own (render/pair_room.py), so the host queues the step while the GPU projects; a
    # render whose pairs did not fit has its step skipped on the device, as a non-finite one is. Needs the deferred
    # NaN guard (nan_guard on, fused Adam, one process) and not `deterministic`; elsewhere renders size exactly.
    speculative_pairs: bool = True
    # Coarse-to-fine: [[step, factor], ...], training views at 1/factor of their resolution from each step on (e.g.
    # [[0, 4], [1000, 2], [3000, 1]]); evaluation and outputs stay at full resolution (train/resolution.py).
    resolution_schedule: Optional[List[Any]] = None
    # Few-view training: every this many steps also render a camera between two near training cameras and fit it to
    # the depth prior's confident pixels (model.prior_points_confidence) seen from there (train/virtual_views.py;
    # needs depth priors); 0: off; "auto": every step when the run has at most virtual_views.AUTO_MAX_VIEWS training
    # views, else off. The weights of its colour and inverse-depth L1:
    virtual_views: Union[int, str] = 0
    virtual_rgb: float = 1.0
    virtual_depth: float = 1.0
    # Each step, after the optimizers, every opacity times (1 - opacity_decay): a sparsity prior that Adam does not
    # rescale, unlike the `opacity` loss (train/opacity_decay.py says why that matters); 0: off.
    opacity_decay: float = 0.0
    # Each training view renders with a random share drop_rate of the primitives left out and the others' opacities
    # divided by 1 - drop_rate (DropGaussian; train/dropout.py); evaluation renders them all. 0: off; "auto":
    # dropout.AUTO_RATE_3 with at most 3 training views, dropout.AUTO_RATE with up to dropout.AUTO_MAX_VIEWS and with
    # more than dropout.AUTO_OFF_MAX_VIEWS, off in between.
    drop_rate: Union[float, str] = 0.0
    # How the rate runs over the run: "constant", or "ramp": rising linearly to drop_rate at the last step
    # (DropGaussian's schedule, r_t = r * t / T; train/dropout.py; needs a fixed train.steps).
    drop_schedule: str = "constant"
    # 0: every primitive as likely to be left out; p > 0: in each view in proportion to (median depth / its depth) ** p,
    # the same share in all (train/dropout.py near_probabilities: near-camera floaters left out more often).
    drop_near: float = 0.0

    def render_options(self) -> dict:
        """The renderer settings every render of the model uses (training, evaluation, queries)."""
        return dict(near=self.near, far=self.far, tile_size=self.tile_size, max_sigmas=self.max_sigmas,
                    alpha_min=self.alpha_min, transmittance_min=self.transmittance_min, alpha_max=self.alpha_max)


@dataclass
class EvalConfig:
    every: int = 1000  # evaluate the held-out views every this many steps (0: only at the end)
    split: str = "test"  # "test" or "train" (the final metrics fall back to train when there is no test split)
    lpips: bool = True  # LPIPS when its weights are on disk (never downloaded)
    lpips_net: str = "alex"
    save_images: bool = True  # write the final test renders as PNG
    max_views: int = 0  # evaluate at most this many views during training (0: all); the final pass uses all


@dataclass
class OutputConfig:
    dir: Optional[str] = None  # None: outputs/<scene name>
    ply: str = "point_cloud.ply"
    checkpoint: str = "checkpoint.pt"
    # train.parallel=model: each rank writes its own share beside checkpoint.pt, then an index (no rank gathers the
    # whole model); false: one file, the whole model gathered in every rank's CPU memory. Either resumes on any N.
    checkpoint_shards: bool = True
    metrics: str = "metrics.json"


@dataclass
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    strategy: StrategyConfig = field(default_factory=StrategyConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)  # the rule of train.steps=auto
    losses: Dict[str, Any] = field(default_factory=lambda: {"l1": 0.8, "dssim": 0.2})
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    imports: List[str] = field(default_factory=list)
    extensions: Dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return _plain(dataclasses.asdict(self))

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=False)

    def copy(self) -> "Config":
        return copy.deepcopy(self)


ALIASES = {
    "steps": "train.steps", "device": "train.device", "eval_every": "eval.every", "seed": "train.seed",
    "background": "train.background", "out": "output.dir", "data": "data.path", "kind": "model.kind",
    "budget": "strategy.max_primitives", "max_primitives": "strategy.max_primitives",
    "sh_degree": "model.sh_degree", "checkpoint_every": "train.checkpoint_every", "batch_size": "train.batch_size",
}
CHOICES = {
    "data.synthetic": ("orbit", "lightfield"),
    "data.split": ("file", "llff", "all", "grid"),  # "grid": light-field folders (their default)
    "model.kind": ("gaussians", "surfels"),
    "model.init": ("auto", "sfm", "depth", "triangulate", "random"),
    "eval.split": ("test", "train"),
    "train.log": ("jsonl", "tensorboard", "none"),
    "eval.lpips_net": ("alex", "vgg", "squeeze"),
    "train.batch_scaling": ("sqrt", "none"),
    "train.dist_backend": ("auto", "nccl", "gloo"),
    "train.parallel": ("data", "model"),
    "train.drop_schedule": ("constant", "ramp"),
}
AUTO_BOOLS = {"train.fused_ssim"}  # true, false or "auto"
POSITIVE = {"data.width", "data.height", "data.downscale", "data.n_train", "model.init_points", "model.init_knn",
            "train.steps", "train.tile_size", "train.batch_size", "train.dist_timeout"}
NON_NEGATIVE = {"model.sh_interval", "model.background_points", "model.prior_points", "train.checkpoint_every", "train.log_every", "train.threads", "eval.every",
                "eval.max_views"}
# Mappings whose keys are free (user names), not fields.
FREE_MAPPINGS = {"losses", "extensions", "model.features", "optim.extras_lr"}
SECTIONS = {f.name: f for f in dataclasses.fields(Config)}
BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}


def all_keys() -> List[str]:
    """Every dotted key a config accepts (free mappings appear as their own key)."""
    keys = []
    for name, f in SECTIONS.items():
        default = f.default_factory()
        if dataclasses.is_dataclass(default):
            keys += [f"{name}.{g.name}" for g in dataclasses.fields(default)]
        else:
            keys.append(name)
    return keys + list(ALIASES)


def _plain(obj):
    """Tuples -> lists so the YAML dump stays plain."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj
