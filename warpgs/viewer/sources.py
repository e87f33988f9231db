"""What the viewer renders: a model alone, or a Trainer's model (live training or a loaded run).

A source turns (viewmat, K, width, height) into an [H, W, 3] float image in [0, 1] through warpgs's own render
path, under torch.no_grad and its lock: the colour, or with `mode` the depth, normals or alpha as colours
(model/maps.py, the same previews as warpgs-render --outputs). It also says where a browser should start (its
training cameras and points).
`version()` changes when the model does, so the viewer knows when to render again.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import List, Optional, Sequence

import numpy as np
import torch

from warpgs.model.maps import MAPS, display_image, render_outputs
from warpgs.model.rendering import render_model


def display_modes(kind: str) -> List[str]:
    """The display modes a model kind can render (normals: surfels only)."""
    modes = []
    for mode in MAPS:
        try:
            render_outputs(kind, (mode,))
        except ValueError:
            continue
        modes.append(mode)
    return modes


@dataclass
class ViewerView:
    """A camera dressed as a training view without an image: what Trainer.render and its extensions read."""

    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    name: str = "viewer"
    index: int = -1
    image: Optional[torch.Tensor] = None


class ModelSource:
    """A model alone (a PLY, or a run without its scene): `render_model` with a fixed background and renderer
    options (TrainConfig.render_options(): near, far, accuracy knobs)."""

    def __init__(self, model, *, background: Optional[torch.Tensor] = None, render_options: Optional[dict] = None,
                 cameras: Sequence = (), label: str = ""):
        self.model = model
        self.device = model.device
        self.background = None if background is None else torch.as_tensor(background, dtype=torch.float32,
                                                                              device=self.device)
        self.render_options = dict(render_options or {})
        self.cameras: List = list(cameras)
        self.label = label or f"{model.num_primitives} {model.kind}"
        self.lock = threading.Lock()  # one render at a time across browsers: each would take every core

    @property
    def kind(self) -> str:
        return self.model.kind

    def render(self, viewmat: np.ndarray, K: np.ndarray, width: int, height: int, mode: str = "rgb") -> torch.Tensor:
        vm = torch.as_tensor(viewmat, dtype=torch.float32, device=self.device)
        k = torch.as_tensor(K, dtype=torch.float32, device=self.device)
        kind = self.model.kind
        with self.lock, torch.no_grad():
            out = render_model(self.model, vm, k, width, height, outputs=render_outputs(kind, (mode,), "display"),
                               background=self.background, **self.render_options)
            return display_image(out, kind, mode)

    def means(self) -> np.ndarray:
        return self.model.means.detach().cpu().numpy()

    def version(self) -> int:
        return 0

    def status(self) -> str:
        return self.label


class TrainerSource:
    """A Trainer's model, rendered as its evaluation renders it (`Trainer.render`: extensions such as the learned
    environment included) while holding `trainer.lock`, which the training loop holds over each step: a frame
    never sees half an optimizer or densification step, and never changes the model (read-only, no autograd)."""

    def __init__(self, trainer):
        self.trainer = trainer
        self.device = trainer.device
        scene = trainer.scene
        self.cameras: List = [scene.camera(i) for i in scene.train] if scene is not None else []

    @property
    def kind(self) -> str:
        return self.trainer.model.kind

    def render(self, viewmat: np.ndarray, K: np.ndarray, width: int, height: int, mode: str = "rgb") -> torch.Tensor:
        tr = self.trainer
        view = ViewerView(torch.as_tensor(viewmat, dtype=torch.float32, device=self.device),
                          torch.as_tensor(K, dtype=torch.float32, device=self.device), int(width), int(height))
        with tr.lock, torch.no_grad():
            kind = tr.model.kind
            return display_image(tr.render(view, render_outputs(kind, (mode,), "display")), kind, mode)

    def means(self) -> np.ndarray:
        with self.trainer.lock:
            return self.trainer.model.means.detach().cpu().numpy()

    def version(self) -> int:
        return self.trainer.step

    def status(self) -> str:
        tr = self.trainer
        return f"step {tr.step} / {tr.max_steps} · {tr.model.num_primitives} {tr.model.kind}"
