"""`warpgs-view --model PATH` -> a render source; every error names the path or option at fault.

PATH is a warpgs-train output folder or a PLY file (3DGS or 2DGS layout). A folder with config.yaml is loaded as
warpgs-render loads it (checkpoint, else its PLY; the scene its config names gives the training cameras and the
extensions, e.g. the learned environment). When that scene cannot be loaded (moved, or another machine), the
folder's PLY is shown on its own, from a camera looking at the model's centre.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional, Tuple

import torch

from warpgs.config.schema import BACKGROUNDS

RUN_FILES = ("config.yaml", "checkpoint.pt", "point_cloud.ply")


def parse_background(text: Optional[str]) -> Optional[Tuple[float, float, float]]:
    """--background: black, white or R,G,B in [0, 1]; None keeps the run's (black for a bare PLY)."""
    if text is None:
        return None
    if text in BACKGROUNDS:
        return BACKGROUNDS[text]
    parts = text.split(",")
    try:
        rgb = tuple(float(p) for p in parts)
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise ValueError(f"--background: expected black, white or R,G,B with each in [0, 1], got {text!r}")
    return rgb


def resolve_device(name: Optional[str]) -> torch.device:
    """--device: cpu, cuda or cuda:N; default CUDA when available."""
    if name is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"--device: expected cpu, cuda or cuda:N, got {name!r}") from None
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"--device: expected cpu, cuda or cuda:N, got {name!r}")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device: {name!r} asked for but CUDA is not available here (use --device cpu)")
    return device


def check_model_path(path) -> Tuple[str, Path]:
    """("run", folder) or ("ply", file), before anything heavy is imported or loaded."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"--model: {p} does not exist (expected a warpgs-train output folder or a .ply file)")
    if p.is_file():
        if p.suffix.lower() != ".ply":
            raise ValueError(f"--model: {p} is not a .ply file (expected a warpgs-train output folder or a .ply file)")
        return "ply", p
    if (p / "config.yaml").is_file():
        return "run", p
    if (p / "point_cloud.ply").is_file():
        return "ply", p / "point_cloud.ply"
    raise FileNotFoundError(f"--model: {p} holds none of {', '.join(RUN_FILES)} "
                            f"(is it a warpgs-train output folder?)")


def load_source(path, device=None, background=None):
    """A ModelSource (PLY) or TrainerSource (run folder) for the viewer; `background` an (r, g, b) or None."""
    from warpgs.viewer.sources import ModelSource

    kind, p = check_model_path(path)
    device = resolve_device(device) if not isinstance(device, torch.device) else device
    if kind == "ply":
        return ModelSource(_read_ply(p, device), background=background or (0.0, 0.0, 0.0))
    return _load_run(p, device, background)


def _read_ply(path: Path, device):
    from warpgs.model.gaussians import load_ply

    try:
        return load_ply(path, device=device)
    except ValueError as e:
        msg = str(e)
        raise ValueError(msg if str(path) in msg else f"{path}: {msg}") from None


def _load_run(run: Path, device, background):
    from warpgs.cli.commands import load_run
    from warpgs.config.loader import load_config
    from warpgs.viewer.sources import ModelSource, TrainerSource

    # The viewer only reads the model: no second viewer, no images kept on the device.
    overrides = ["train.viewer=false", "data.preload=false"]
    try:
        trainer = load_run(run, device.type if device.index is None else str(device), overrides)
    except (FileNotFoundError, ValueError) as e:
        try:
            config = load_config(run / "config.yaml")
        except ValueError:
            raise ValueError(f"{run / 'config.yaml'}: {e}") from None
        ply = run / config.output.ply
        if not ply.is_file():
            raise
        print(f"warpgs-view: cannot load the run in {run} ({e}); showing {ply.name} without its training "
              f"cameras", file=sys.stderr)
        bg = background or (config.train.background if isinstance(config.train.background, list) else
                            BACKGROUNDS.get(config.train.background, (0.0, 0.0, 0.0)))
        return ModelSource(_read_ply(ply, device), background=bg, render_options=config.train.render_options())
    if background is not None:
        if "environment" in trainer.modules:  # its renders composite the learned map over a zero background
            print("warpgs-view: --background ignored: this run learned its background (the environment "
                  "extension)", file=sys.stderr)
        else:
            trainer.background = torch.tensor(background, dtype=torch.float32, device=trainer.device)
    return TrainerSource(trainer)
