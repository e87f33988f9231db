"""What the trainer builds before step 0: device, scene, background, initial model. Plain functions so that
scripts (benchmarks, notebooks) can build the same pieces without a Trainer."""
from __future__ import annotations

import copy
import dataclasses
import re
import shutil
import sys
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from warpgs.config.loader import BACKGROUNDS, Config, DataConfig
from warpgs.model.gaussians import MODEL_KINDS, GaussianModel
from warpgs.model.rendering import focal_length
from warpgs.train.lifted_prior import confidence_for, lifted_prior
from warpgs.train.virtual_views import virtual_every


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"train.device: {name!r} asked for but CUDA is not available (use device=cpu)")
    return device


def install_training_ssim(fused, device: torch.device) -> None:
    """train.fused_ssim: the D-SSIM through Warp kernels (render/ssim_op.py) or torch's filtering, replayed from
    CUDA graphs on a GPU (losses/cuda_graphs.py); "auto" picks Warp's on CUDA only, where it is the faster."""
    from warpgs.losses import photometric
    from warpgs.render.ssim_op import fused_ssim

    if fused == "auto":
        fused = device.type == "cuda"
    photometric.use_training_ssim(fused_ssim if fused else None)


def scene_label(data: DataConfig) -> str:
    """A short name for the scene: the folder name, or synthetic-<kind>."""
    if data.path is None:
        return f"synthetic-{data.synthetic}"
    name = Path(data.path).resolve().name
    return re.sub(r"[^\w.-]+", "_", name) or "scene"


def what_reads_priors(cfg: Config, terms, num_train_views: int) -> str:
    """What in the config reads the scene's depth priors, for messages ("" if nothing): loss terms that declare the
    prior batch field (register_loss(batch=...)), model.prior_points and train.virtual_views (with "auto", when it
    is on for this many training views)."""
    from warpgs.losses import required_batch_fields
    from warpgs.losses.marr import PRIOR_KEY

    readers = [f"losses.{name}" for name in required_batch_fields(terms).get(PRIOR_KEY, [])]
    readers += [key for key, on in (("model.prior_points", cfg.model.prior_points > 0),
                                    ("train.virtual_views", virtual_every(cfg.train.virtual_views, num_train_views)))
                if on]
    return ", ".join(readers)


def load_training_scene(data: DataConfig, out_dir: Optional[Path] = None,
                        readers: Optional[Callable[[int], str]] = None):
    """The scene a config names (data.path None: the built-in synthetic scene, generated once and cached).
    data.depth_priors "estimate" runs the built-in plane-sweep stereo on the training views, aligns it to the SfM
    points and writes the priors to <out_dir>/depth_priors (never into the scene's own folder); a later Trainer on
    the same output folder (resume, warpgs-render/eval) reuses them, and one with another output folder copies them
    from the user's cache when the images, cameras, views, points and settings are the same (_estimated_priors).
    readers(number of training views): what in the config reads depth priors ("" if nothing; what_reads_priors):
    with "auto" a scene without priors for its training views then gets estimated ones, as with "estimate"; with
    "none" that is an error, named here rather than at the first step."""
    from warpgs.data import compute_depth_priors, default_scene, load_scene
    from warpgs.data.exclude import excluding

    path = default_scene(data.synthetic, data.width, data.height) if data.path is None else Path(data.path)
    scene = excluding(load_scene(path, split=data.split, n_train=data.n_train, downscale=data.downscale), data.exclude)
    prior = data.depth_priors
    needs_priors = readers(len(scene.train)) if readers is not None else ""
    if needs_priors and prior == "auto" and not scene.has("depth_prior", scene.train):
        print(f"depth priors: the scene at {scene.root} has none for its training views and {needs_priors} read "
              f"them: estimating them (data.depth_priors=auto; 'none' or a folder to choose otherwise)",
              file=sys.stderr)
        prior = "estimate"
    if needs_priors and prior in (None, "none"):
        raise ValueError(f"data.depth_priors: 'none', but {needs_priors} read depth priors (use 'auto' or "
                         f"'estimate', or turn those off)")
    if prior in (None, "none"):
        if scene.has("depth_prior"):
            scene = copy.copy(scene)
            scene.files = [dataclasses.replace(f, depth_prior=None) for f in scene.files]
    elif prior == "estimate":
        if out_dir is None:
            raise ValueError("data.depth_priors: 'estimate' needs an output folder to write the priors to")
        scene = _estimated_priors(scene, Path(out_dir) / "depth_priors", compute_depth_priors,
                                  plane_sweep(data.depth_prior_options), data.depth_prior_fill)
    elif prior != "auto":
        folder = Path(prior)
        if not folder.is_absolute() and not folder.is_dir():
            folder = scene.root / prior
        scene = scene.with_depth_priors(folder)
    if not scene.train:
        left_out = " after data.exclude" if scene.metadata.get("excluded") else ""
        raise ValueError(f"data.split: the scene at {scene.root} has no training views{left_out}")
    if needs_priors:
        from warpgs.data.depth.coverage import describe_prior_coverage, prior_coverage

        coverage = prior_coverage(scene, scene.train)
        if coverage is not None:
            print(describe_prior_coverage(coverage), file=sys.stderr)
    return scene


def warn_pose_jumps(scene, say=None) -> list:
    """Warn (through `say`, default stderr) when a video capture's poses jump between neighbouring frames
    (warpgs.data.pose_checks): those frames contradict the rest and training fits them anyway. When every jump is a
    half turn (SfM folded the orbit in half), the warning names the two consistent halves and the data.exclude that
    keeps the larger one. Returns the jumps."""
    from warpgs.data.pose_checks import folded_halves, scene_pose_jumps, side_ranges

    jumps = scene_pose_jumps(scene)
    if jumps:
        listed = ", ".join(f"{j['from']} -> {j['to']} ({j['turn_deg']:.0f} deg)" for j in jumps[:5])
        message = (f"warning: {scene.root}: the poses jump between neighbouring frames: {listed}"
                   + (f" and {len(jumps) - 5} more" if len(jumps) > 5 else "")
                   + ". SfM may have put the frames between such jumps on the wrong side of the scene "
                   "(warpgs.data.pose_checks; benchmarks/pose_continuity.py in the source tree)")
        halves = folded_halves(scene.native_cameras)
        if halves:
            (larger, size), (smaller, smaller_size) = map(side_ranges, halves)
            message += (f". Every jump is a half turn: the orbit is likely folded in half, each half consistent in "
                        f"itself: {larger} ({size} frames) and {smaller} ({smaller_size}). "
                        f"Train on the larger with data.exclude=[{smaller}]")
        else:
            message += "; data.exclude=[NAME, ...] leaves such frames out"
        (say or (lambda m: print(m, file=sys.stderr)))(message)
    return jumps


def plane_sweep(options: Optional[dict]):
    """The built-in estimator with data.depth_prior_options; a bad option is named."""
    from warpgs.data import PlaneSweepStereo

    try:
        return PlaneSweepStereo(**(options or {}))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"data.depth_prior_options: {exc}") from exc


def _estimated_priors(scene, folder: Path, compute, estimator, fill_confidence: float = 0.0):
    """The priors already estimated into `folder` when complete and made by the same estimator settings and fill;
    else a copy of the same priors from the user's cache ($WARPGS_CACHE/depth_priors/<key>: the same images,
    cameras, views, SfM points and settings, made by an earlier run with another output folder); else new ones,
    copied into that cache for the next run."""
    from warpgs.data.cache import cache_dir, publish_folder, touch
    from warpgs.data.depth.priors import prior_key

    done = _complete_priors(scene, folder, estimator, fill_confidence)
    if done is not None:
        return done
    shared = cache_dir() / "depth_priors" / prior_key(scene, scene.train, estimator, fill_confidence)
    if _complete_priors(scene, shared, estimator, fill_confidence) is not None:
        shutil.copytree(shared, folder, dirs_exist_ok=True)
        touch(shared)
        print(f"depth priors: estimated by an earlier run on these views, copied from {shared}", file=sys.stderr)
        return _complete_priors(scene, folder, estimator, fill_confidence)
    made = compute(scene, estimator, out_dir=folder, fill_confidence=fill_confidence)[0]
    publish_folder(folder, shared, what="depth priors")
    return made


def _complete_priors(scene, folder: Path, estimator, fill_confidence: float):
    """The scene with the priors in `folder` when every training view has one (format.json is written last) and
    they were made with these estimator settings and fill; else None."""
    from warpgs.data.depth.priors import estimator_settings
    from warpgs.data.errors import read_json
    from warpgs.data.formats.view_files import FORMAT_FILE
    from warpgs.data.scene import MapFormat

    if not (folder / FORMAT_FILE).is_file():
        return None
    done = scene.with_depth_priors(folder, MapFormat("inverse_depth"))
    made, settings = read_json(folder / FORMAT_FILE), estimator_settings(estimator)
    # A folder from before settings were recorded counts as made by these ones.
    same = (float(made.get("fill_confidence", 0.0)) == float(fill_confidence)
            and made.get("estimator_settings", settings) == settings)
    return done if same and all(done.files[v].depth_prior is not None for v in scene.train) else None


def resolve_background(spec, scene, device) -> torch.Tensor:
    """[3] float tensor: "auto" -> the scene's background (e.g. white for NeRF-synthetic) else black."""
    if isinstance(spec, str):
        if spec == "auto":
            bg = getattr(scene, "background", None)
            rgb = (0.0, 0.0, 0.0) if bg is None else tuple(float(v) for v in np.asarray(bg).reshape(-1)[:3])
        else:
            rgb = BACKGROUNDS[spec]
    else:
        rgb = tuple(float(v) for v in spec)
    return torch.tensor(rgb, dtype=torch.float32, device=device)


def initial_points(scene, config: Config):
    """(xyz [N,3], rgb [N,3] float tensors, source) following model.init."""
    from warpgs.data.sfm import init_points as ip

    how, n, seed = config.model.init, config.model.init_points, config.train.seed
    # Points triangulated from known poses are cached in the output folder (a resumed run reuses them) and in the
    # user's cache (every later run on the same capture and views reuses them: minutes of features and matching).
    from warpgs.data.cache import cache_dir

    tri_dir = Path(config.output.dir) / "triangulation" if config.output.dir else None
    shared = cache_dir() / "triangulation"
    if how == "auto":
        cloud, source = ip.initial_points(scene, n=n, seed=seed, triangulate_dir=tri_dir, shared_dir=shared)
    elif how == "triangulate":
        if tri_dir is None:
            raise ValueError("model.init: 'triangulate' needs an output folder to cache the points in")
        # With the prior's lifted points beside them (model.prior_points), a thin triangulation (12 views around a
        # capture's textureless backdrop can give 19 points) is only part of the start, not a reason to stop.
        cloud, source = ip.triangulated_points(scene, tri_dir, strict=True, thin_ok=bool(config.model.prior_points),
                                               shared_dir=shared)
    elif how == "sfm":
        if scene.points is None or len(scene.points) == 0:
            raise ValueError(f"model.init: 'sfm' but the scene at {scene.root} has no SfM points (use auto/random)")
        cloud, source = scene.points, "sfm"
    elif how == "depth":
        src = "prior" if scene.has("depth_prior") else "depth"
        cloud, source = ip.points_from_depth(scene, n=n, source=src, seed=seed), f"depth ({src})"
    else:
        try:
            cloud, source = ip.random_points(scene, n=n, seed=seed), "random"
        except ValueError:  # parallel optical axes (a camera array): a box around the cameras instead
            centres = np.stack([c.center for c in scene.cameras])
            extent = scene.camera_extent()
            rng = np.random.default_rng(seed)
            lo, hi = centres.min(0) - 3 * extent, centres.max(0) + 3 * extent
            from warpgs.data.points import PointCloud

            cloud, source = PointCloud(rng.uniform(lo, hi, (n, 3)), rng.uniform(0, 1, (n, 3))), "random (box)"
    xyz, rgb = cloud.tensors()
    xyz, rgb = xyz.float(), rgb.float()
    if config.model.prior_points:
        confidence = confidence_for(config.model.prior_points_confidence, len(scene.train))
        px, pc, note = prior_points(scene, config.model.prior_points, confidence, seed)
        xyz, rgb = torch.cat([xyz, px]), torch.cat([rgb, pc])
        source += f" + {note}"
    if config.model.background_points:
        bx, bc = background_points(scene, xyz, config.model.background_points, config.model.background_radius, seed)
        xyz, rgb = torch.cat([xyz, bx]), torch.cat([rgb, bc])
        source += f" + {len(bx)} background"
    return xyz, rgb, source


def prior_points(scene, n: int, min_confidence: float, seed: int = 0):
    """(xyz, rgb, description) of n points lifted from the training views' depth priors at pixels of at least
    min_confidence (model.prior_points): the dense 2.5D sketch as a starting point where triangulating a few
    views finds only hundreds of points. A scene without priors is an error naming the key."""
    cloud = lifted_prior(scene, scene.train, n, min_confidence, seed + 1, "model.prior_points",
                         f"model.prior_points={n}")
    xyz, rgb = cloud.tensors()
    has_confidence = any(scene.prior_confidence_np(v) is not None for v in scene.train)
    which = f"confidence >= {min_confidence:g}" if has_confidence else "the prior files carry no confidence: any valid pixel"
    return xyz.float(), rgb.float(), f"{len(xyz)} from depth priors ({which})"


def background_points(scene, points: torch.Tensor, n: int, radius: float, seed: int = 0):
    """n grey points uniformly on a sphere around the cameras' centre, `radius` times the scene's radius (the
    farthest camera or 99th-percentile point). Scenes with sky get somewhere far away to put it, instead of
    floaters in front of the cameras that haze every novel view."""
    centres = torch.as_tensor(np.stack([c.center for c in scene.cameras]), dtype=torch.float32)
    centre = centres.mean(0)
    reach = float((centres - centre).norm(dim=1).max())
    if len(points):
        dist = (points - centre).norm(dim=1)
        dist = dist[::-(-len(dist) // 2**24)]  # torch.quantile refuses more than 2^24 values: an even subsample
        reach = max(reach, float(torch.quantile(dist, 0.99)))
    gen = torch.Generator().manual_seed(int(seed) + 1)
    d = torch.randn(int(n), 3, generator=gen)
    d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return centre + radius * max(reach, 1e-3) * d, torch.full((int(n), 3), 0.5)


def build_model(scene, config: Config, device) -> tuple:
    """(model, init source): primitives of model.kind from the initial points, at most the strategy budget."""
    xyz, rgb, source = initial_points(scene, config)
    cls = MODEL_KINDS[config.model.kind]
    gen = torch.Generator().manual_seed(int(config.train.seed))
    model: GaussianModel = cls.from_points(xyz, rgb, sh_degree=config.model.sh_degree,
                                           opacity=config.model.init_opacity, knn=config.model.init_knn,
                                           max_points=config.strategy.max_primitives, generator=gen)
    for name, dim in config.model.features.items():
        model.add_extra(name, torch.zeros(model.num_primitives, int(dim)))
    return model.to(device), source


def active_sh_degree(step: int, config: Config, max_degree: int) -> int:
    interval = config.model.sh_interval
    return max_degree if interval <= 0 else min(max_degree, step // interval)


def scene_extent(scene, override: Optional[float]) -> float:
    return float(override) if override else float(scene.camera_extent())


def training_focal(scene) -> float:
    """The median focal length (pixels, sqrt(fx fy)) of the scene's training cameras at the served resolution (all
    cameras when none is marked for training; 0 without cameras)."""
    cams = [scene.cameras[i] for i in scene.train] or list(scene.cameras)
    return float(np.median([focal_length(c.K) for c in cams])) if cams else 0.0
