"""Command-line tools: `warpgs-train`, `warpgs-render`, `warpgs-eval` (also `python -m warpgs.cli train|render|eval`).

    warpgs-train [CONFIG] [--data PATH] [--out DIR] [--resume] [--nproc N] [key=value ...]
    warpgs-render --model OUT [--orbit N [--video [--fps F]]] [--split test|train] [--outputs rgb,depth,normal,alpha]
    warpgs-eval --model OUT [--split test|train] [--no-lpips] [--save-images]

CONFIG is a YAML file or the name of a preset in configs/ (default, gaussians, surfels, ...). With no CONFIG,
configs/default.yaml: the built-in synthetic scene, about two minutes on a 2-core CPU; with --data and no CONFIG,
configs/gaussians.yaml (the real-capture recipe). --data may name a video: see warpgs-process (cli/process.py).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import List, Optional, Sequence

from warpgs.cli.common import EXIT_CONFIG, EXIT_DISTRIBUTED, EXIT_INTERRUPTED, EXIT_NONFINITE, report_error

# The no-argument run, used when configs/default.yaml is not on disk (an installed wheel without the configs
# folder); tests check that the file and this copy agree.
QUICK_RUN = {
    "data": {"path": None, "synthetic": "orbit", "width": 128, "height": 96},
    "model": {"kind": "gaussians", "sh_degree": 3, "sh_interval": 500},
    "optim": {"means_lr": 1.6e-4, "means_lr_final": 1.6e-6},
    "strategy": {"refine_start": 100, "refine_every": 100, "refine_stop": 800, "reset_every": 0,
                 "prune_world_scale": 0, "prune_screen_radius": 0, "max_primitives": 20000},
    "losses": {"l1": 0.8, "dssim": 0.2},
    "extensions": {"environment": {"degree": 3, "lr": 0.01}},
    "train": {"steps": 1000, "device": "auto", "checkpoint_every": 500},
    "eval": {"every": 500},
}


def configs_dir() -> Path:
    """The YAML presets: configs/ beside the package in a source checkout (or editable install), else the copy
    a wheel ships as warpgs/configs."""
    package = Path(__file__).resolve().parent.parent  # warpgs/
    source = package.parent / "configs"
    return source if source.is_dir() else package / "configs"


def resolve_config_source(name: Optional[str]):
    """CONFIG argument -> a YAML path or the built-in quick-run mapping."""
    if name is None:
        path = configs_dir() / "default.yaml"
        return path if path.is_file() else QUICK_RUN
    path = Path(name)
    if path.is_file():
        return path
    for cand in (configs_dir() / name, configs_dir() / f"{name}.yaml"):
        if cand.is_file():
            return cand
    if name == "default":
        return QUICK_RUN
    presets = sorted(p.stem for p in configs_dir().glob("*.yaml")) if configs_dir().is_dir() else []
    raise FileNotFoundError(f"config {name!r}: no such file" + (f" or preset (presets: {presets})" if presets else ""))


def _split_args(items: Sequence[str]) -> tuple:
    config, overrides = None, []
    for item in items:
        if "=" in item:
            overrides.append(item)
        elif config is None:
            config = item
        else:
            raise SystemExit(f"warpgs-train: error: more than one CONFIG given ({config!r}, {item!r}); "
                             f"overrides look like key=value")
    return config, overrides


def _exit_with_broken_group(code: int) -> int:
    """End the process now when a collective failed. A normal interpreter exit races the process group's worker
    thread, which still holds the failed work: it is killed while taking the GIL and the process aborts with
    SIGABRT instead of `code` (seen on CI). No clean-up is lost: checkpoints and outputs are written atomically.
    Without a live group (the error came from elsewhere, or in-process callers) the code is returned as usual."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


# ----- warpgs-train -------------------------------------------------------------------------------------------
def train_main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="warpgs-train", description="Train Gaussians or surfels on a scene.",
                                 epilog="overrides: dotted keys (optim.means_lr=1e-4, losses.dssim=0) or aliases "
                                        "steps=N device=cpu|cuda eval_every=N seed=N budget=N kind=surfels")
    ap.add_argument("args", nargs="*", metavar="[CONFIG] [key=value]",
                    help="a YAML file or preset name, then overrides")
    ap.add_argument("--data", help="scene folder: COLMAP (images/ + sparse/0/, optional split.json), "
                                   "transforms.json, or a light-field folder; or a video (.mp4, .mov, ...), first "
                                   "turned into a scene folder beside it as warpgs-process does (reused next time). "
                                   "With --data and no CONFIG the preset is 'gaussians' (the real-capture recipe); "
                                   "without --data, 'default' (the built-in demo scene)")
    ap.add_argument("--out", help="output folder (default: outputs/<scene name>)")
    ap.add_argument("--resume", action="store_true", help="continue from the checkpoint in the output folder")
    ap.add_argument("--quiet", action="store_true", help="no progress line")
    ap.add_argument("--print-config", action="store_true", help="print the resolved config and exit")
    ap.add_argument("--nproc", type=int, metavar="N",
                    help="data-parallel training on N processes of this machine (one per GPU; gloo on the CPU), "
                         "launched through torchrun; train.batch_size counts the views of a step over all of them")
    # Intermixed: CONFIG, options and key=value overrides in any order (plain parse_args stops collecting the
    # positionals at the first option, so `gaussians --data X steps=10` failed on steps=10).
    args = ap.parse_intermixed_args(argv)
    config_name, overrides = _split_args(args.args)

    from warpgs.config.loader import ConfigError, load_config

    try:
        source = resolve_config_source(config_name or _implied_preset(args, overrides))
        config = load_config(source, overrides)
        _apply_paths(config, args)
        if args.resume and config_name is None:
            # Without a CONFIG, continue with the run's own saved config (plus these overrides).
            saved = _saved_config(config)
            if saved is not None:
                config = load_config(saved, overrides)
                _apply_paths(config, args)
    except (ConfigError, FileNotFoundError) as e:
        return report_error("warpgs-train", str(e), EXIT_CONFIG)
    if args.print_config:
        print(config.to_yaml(), end="")
        return 0
    if args.data and _is_video(args.data):  # before --nproc: the workers then find the scene ready
        try:
            _scene_from_video_once(args.data, quiet=args.quiet)
        except (ValueError, FileNotFoundError) as e:
            return report_error("warpgs-train", str(e), EXIT_CONFIG)
    if args.nproc is not None:
        from warpgs.cli.launch import check_nproc, launch_train

        try:
            check_nproc(args.nproc)
            if args.nproc > 1:  # else the plain single-process run below
                return launch_train(args.nproc, list(sys.argv[1:] if argv is None else argv))
        except ValueError as e:
            return report_error("warpgs-train", str(e), EXIT_CONFIG)

    from warpgs.train.trainer import DistributedError, NonFiniteError, Trainer

    try:
        trainer = Trainer(config, resume=args.resume, quiet=args.quiet)
    except (ValueError, FileNotFoundError) as e:  # bad config, scene or checkpoint: the message names it
        return report_error("warpgs-train", str(e), EXIT_CONFIG)
    except DistributedError as e:
        report_error("warpgs-train", str(e), EXIT_DISTRIBUTED)
        return _exit_with_broken_group(EXIT_DISTRIBUTED)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    try:
        result = trainer.fit()
    except KeyboardInterrupt:
        trainer.close()
        return EXIT_INTERRUPTED
    except NonFiniteError:
        trainer.close()
        return EXIT_NONFINITE
    except ImportError as e:  # an optional extra the config asks for (train.viewer, train.log=tensorboard)
        trainer.close()
        return report_error("warpgs-train", str(e), EXIT_CONFIG)
    except DistributedError as e:  # the group is broken: leave it to the process's exit, not a collective teardown
        # Rank 0's loop has said it already; the other ranks are quiet, so their error is printed here.
        if trainer.quiet:
            report_error("warpgs-train", str(e), EXIT_DISTRIBUTED)
        return _exit_with_broken_group(EXIT_DISTRIBUTED)
    trainer.close()
    if not trainer.ranks.is_main:  # rank 0 prints the summary
        return 0
    out = result.out_dir
    m = result.metrics
    renders = out / "renders" / m["split"]
    n_png = len(list(renders.glob("*.png"))) if renders.is_dir() else 0
    lp = f"lpips {m['lpips']:.4f}" if m.get("lpips") is not None else "lpips unavailable"
    print(f"\nresults in {out.resolve()}\n"
          f"  {config.output.ply:<18} {result.num_primitives} {trainer.model.kind}\n"
          f"  {config.output.metrics:<18} {m['split']} psnr {m['psnr']:.2f} ssim {m['ssim']:.4f} {lp}; "
          f"{result.steps} steps in {result.train_seconds:.1f} s\n"
          f"  {'renders/' + m['split'] + '/':<18} {n_png} PNG\n"
          f"  {config.output.checkpoint:<18} continue with: warpgs-train --out {out} --resume steps=N\n"
          f"render an orbit: warpgs-render --model {out} --orbit 60")
    return 0


def _implied_preset(args, overrides: Sequence[str]) -> Optional[str]:
    """The preset when no CONFIG is given: a scene of the user's (--data, or a data.path override) trains with
    the real-capture recipe `gaussians`; only the built-in demo scene gets `default` (None)."""
    def names_a_scene(item: str) -> bool:
        key, _, value = item.partition("=")
        return key.strip() in ("data", "data.path") and value.strip().lower() not in ("", "null", "none", "~")

    return "gaussians" if args.data or any(names_a_scene(item) for item in overrides) else None


def _scene_from_video_once(video, quiet: bool) -> Path:
    """The scene folder of `--data VIDEO`, made on the first call. The ranks of a distributed run started
    without --nproc (torchrun itself) would each write it at once, so they only reuse a finished one."""
    from warpgs.cli.process import scene_from_video
    from warpgs.data.video.scene import finished_scene, video_scene_dir
    from warpgs.train.distributed import env_world_size

    out = video_scene_dir(video)
    if finished_scene(video, out):  # made earlier, by this command or by warpgs-process with any --frames
        return out
    if env_world_size() > 1:
        raise ValueError(f"--data {video}: in a distributed run, make the scene first: warpgs-process {video}")
    return scene_from_video(video, out, progress=not quiet)


def _is_video(path) -> bool:
    from warpgs.data.video.decode import is_video  # here: importing warpgs.data loads torch, slow for --help

    return is_video(path)


def _apply_paths(config, args) -> None:
    """--data / --out as given (not through YAML parsing, which would mangle some paths); a video's scene is
    the folder warpgs-process makes beside it."""
    if args.data:
        if _is_video(args.data):
            from warpgs.data.video.scene import video_scene_dir

            config.data.path = str(video_scene_dir(args.data))
        else:
            config.data.path = str(args.data)
    if args.out:
        config.output.dir = str(args.out)


def _saved_config(config) -> Optional[Path]:
    from warpgs.train.setup import scene_label

    out = Path(config.output.dir) if config.output.dir else Path("outputs") / scene_label(config.data)
    path = out / "config.yaml"
    return path if path.is_file() else None


# ----- loading a trained model --------------------------------------------------------------------------------
def load_run(model_dir, device: Optional[str] = None, overrides: Sequence[str] = ()):
    """A Trainer restored from a run folder (its config.yaml and checkpoint), for rendering and evaluation.
    Falls back to the folder's PLY when the checkpoint is missing."""
    from warpgs.config.loader import load_config
    from warpgs.model.gaussians import load_ply
    from warpgs.train.trainer import Trainer

    run = Path(model_dir)
    cfg_path = run / "config.yaml"
    if not cfg_path.is_file():
        raise FileNotFoundError(f"{run}: no config.yaml (is this a warpgs-train output folder?)")
    config = load_config(cfg_path, ([f"train.device={device}"] if device else []) + list(overrides))
    config.output.dir = str(run)
    if (run / config.output.checkpoint).is_file():
        return Trainer(config, resume=True, quiet=True)
    ply = run / config.output.ply
    if not ply.is_file():
        raise FileNotFoundError(f"{run}: neither {config.output.checkpoint} nor {config.output.ply} found")
    trainer = Trainer(config, model=load_ply(ply), quiet=True)
    trainer.step = trainer.max_steps  # train.steps=auto has no fixed count: its bound stands for a finished run
    return trainer


# ----- warpgs-render ------------------------------------------------------------------------------------------
def render_main(argv: Optional[List[str]] = None) -> int:
    from warpgs.cli.outputs import DEFAULT_DEPTH_SCALE

    ap = argparse.ArgumentParser(prog="warpgs-render", description="Render a trained model to PNG files.")
    ap.add_argument("--model", required=True, help="a warpgs-train output folder")
    ap.add_argument("--orbit", type=int, metavar="N", help="render N views on an orbit instead of the test cameras")
    ap.add_argument("--split", default="test", choices=("test", "train"), help="cameras to render (default test)")
    ap.add_argument("--out", help="where the PNGs go (default: MODEL/renders/<split> or MODEL/renders/orbit)")
    ap.add_argument("--device", help="cpu, cuda, ... (default: the run's)")
    ap.add_argument("--outputs", default="rgb", metavar="LIST",
                    help="comma-separated maps to write per view: rgb, depth (EXR, 16-bit PNG x --depth-scale and a "
                         "coloured preview; surfels: median depth, 3D Gaussians: expected depth), normal (EXR and "
                         "an RGB preview; surfels only), alpha (default rgb)")
    ap.add_argument("--depth", action="store_true", help="the same as adding depth to --outputs")
    ap.add_argument("--depth-scale", type=float, default=DEFAULT_DEPTH_SCALE, metavar="S",
                    help=f"the 16-bit depth PNGs hold depth x S (default {DEFAULT_DEPTH_SCALE:g}: millimetres for a "
                         f"scene in metres); depth beyond 65535 / S is 0 there (the EXR keeps it)")
    ap.add_argument("--video", action="store_true",
                    help="with --orbit: also write the views as OUT/orbit.mp4 (pip install 'warpgs[video]')")
    ap.add_argument("--fps", type=float, default=30.0, help="frames per second of --video (default 30)")
    args = ap.parse_args(argv)
    from warpgs.model.maps import parse_maps

    try:
        maps = parse_maps(args.outputs + (",depth" if args.depth else ""))
        if not 0 < args.depth_scale < float("inf"):
            raise ValueError(f"--depth-scale: expected a positive number, got {args.depth_scale}")
    except ValueError as e:
        return report_error("warpgs-render", str(e), EXIT_CONFIG)
    if args.video:  # before loading anything: a missing extra should not cost a scene load and half the renders
        from warpgs.cli.video import VideoUnavailable, check_video_support

        if args.orbit is None:
            return report_error("warpgs-render", "--video needs --orbit N (the frames of the video)", EXIT_CONFIG)
        if not args.fps > 0:
            return report_error("warpgs-render", f"--fps: expected a positive number, got {args.fps}", EXIT_CONFIG)
        try:
            check_video_support()
        except VideoUnavailable as e:
            return report_error("warpgs-render", str(e), EXIT_CONFIG)
    try:
        trainer = load_run(args.model, args.device)
    except (ValueError, FileNotFoundError) as e:
        return report_error("warpgs-render", str(e), EXIT_CONFIG)
    import contextlib

    import torch

    from warpgs.cli.outputs import MapStats, write_maps
    from warpgs.model.maps import render_outputs

    kind = trainer.model.kind
    try:
        outputs = render_outputs(kind, maps + (("rgb",) if args.video else ()))
    except ValueError as e:
        return report_error("warpgs-render", str(e), EXIT_CONFIG)
    if args.orbit is not None:
        from warpgs.cli.orbit import orbit_cameras

        scene = trainer.scene
        cams = [scene.cameras[i] for i in (scene.test or scene.train)] + [scene.cameras[i] for i in scene.train]
        points = scene.points.xyz if scene.points is not None else None
        try:
            cameras = orbit_cameras(cams, args.orbit, points)
        except ValueError as e:
            return report_error("warpgs-render", str(e), EXIT_CONFIG)
        views = [_CameraView(c, trainer.device) for c in cameras]
        label = "orbit"
    else:
        split, views = trainer.eval_views(args.split)
        label = split
    out_dir = Path(args.out) if args.out else Path(args.model) / "renders" / label
    t0 = time.perf_counter()
    if args.video:
        from warpgs.cli.video import Mp4Writer

        video = Mp4Writer(out_dir / f"{label}.mp4", args.fps)
    else:
        video = contextlib.nullcontext()
    stats = MapStats()
    with torch.no_grad(), video:
        for v in views:
            r = trainer.render(v, outputs)
            write_maps(out_dir, Path(v.name).stem, maps, r, kind, stats, args.depth_scale)
            if args.video:
                video.append(r.rgb.clamp(0, 1).cpu().numpy())
    dt = time.perf_counter() - t0
    print(f"rendered {len(views)} views ({', '.join(maps)}: {stats.files} files) of "
          f"{trainer.model.num_primitives} {kind} in {dt:.2f} s ({len(views) / max(dt, 1e-9):.1f} views/s) "
          f"to {out_dir.resolve()}")
    if stats.depth_beyond_png:
        print(f"note: {stats.depth_beyond_png} depth pixels lie beyond 65535 / {args.depth_scale:g} and are 0 in "
              f"the 16-bit PNGs (the EXRs hold them); a smaller --depth-scale keeps them")
    if args.video:
        print(f"video: {video.path.resolve()} ({video.frames} frames at {args.fps:g} fps)")
    return 0


class _CameraView:
    """A camera dressed as a View (no image) for rendering."""

    def __init__(self, cam, device):
        self.name, self.width, self.height = cam.name, cam.width, cam.height
        self.viewmat, self.K = cam.viewmat_tensor(device), cam.K_tensor(device)
        self.index, self.image = -1, None


# ----- warpgs-eval --------------------------------------------------------------------------------------------
def eval_main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="warpgs-eval", description="Recompute the metrics of a trained model.")
    ap.add_argument("--model", required=True, help="a warpgs-train output folder")
    ap.add_argument("--split", default="test", choices=("test", "train"))
    ap.add_argument("--device", help="cpu, cuda, ... (default: the run's)")
    ap.add_argument("--no-lpips", action="store_true", help="skip LPIPS")
    ap.add_argument("--save-images", action="store_true", help="also write the renders (MODEL/renders/<split>)")
    args = ap.parse_args(argv)
    overrides = [f"eval.split={args.split}"] + (["eval.lpips=false"] if args.no_lpips else [])
    try:
        trainer = load_run(args.model, args.device, overrides)
    except (ValueError, FileNotFoundError) as e:
        return report_error("warpgs-eval", str(e), EXIT_CONFIG)
    from warpgs.metrics.views import write_json

    m = trainer.evaluate(save_images=args.save_images)
    result = {"split": m["split"], "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"]}
    if "lpips_unavailable" in m:
        result["lpips_unavailable"] = m["lpips_unavailable"]
    result.update({"num_primitives": trainer.model.num_primitives, "steps": trainer.step,
                   "num_views": m["num_views"], "per_view": m["per_view"]})
    path = write_json(Path(args.model) / f"eval_{m['split']}.json", result)
    print(f"{'view':<24} {'psnr':>7} {'ssim':>7}" + (f" {'lpips':>7}" if m["lpips"] is not None else ""))
    for name, s in m["per_view"].items():
        print(f"{name:<24} {s['psnr']:7.2f} {s['ssim']:7.4f}" + (f" {s['lpips']:7.4f}" if "lpips" in s else ""))
    lp = f" lpips {m['lpips']:.4f}" if m["lpips"] is not None else f" lpips unavailable ({m['lpips_unavailable']})"
    print(f"{m['split']} mean: psnr {m['psnr']:.2f} ssim {m['ssim']:.4f}{lp}; "
          f"{trainer.model.num_primitives} primitives -> {path}")
    return 0


COMMANDS = {"train": train_main, "render": render_main, "eval": eval_main}


def main(argv: Optional[List[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in COMMANDS:
        print(f"usage: python -m warpgs.cli {{{','.join(COMMANDS)}}} ...", file=sys.stderr)
        return EXIT_CONFIG
    return COMMANDS[argv[0]](argv[1:])


if __name__ == "__main__":
    sys.exit(main())
