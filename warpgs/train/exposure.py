"""Per-view exposure: the `exposure` trainer extension.

    extensions: {exposure: {lr: 0.001}}        # warpgs-train gaussians extensions.exposure.lr=0.001

Photos of one capture are often not taken at one exposure: a phone or a video adjusts exposure and white balance
from frame to frame. Without a model of it the primitives fit each photo's brightness, with view-dependent colour
and floaters in front of the cameras. This extension learns, for each training view k, an affine colour transform
A_k (3x3 and an offset) applied to that view's training render, rgb -> A_k [rgb, 1], fitted with its own Adam
group; the model then holds one appearance. Which one is a free choice (scaling every A_k and the colours the other
way renders the same training images), so the transforms are kept to a mean of identity over the training views:
the model's appearance is the captures' average exposure. Held-out, test and every output render (no gradient)
show the model as it is, untransformed; so does any camera that is not a training view.

List it after `environment`: the camera's exposure applies to the whole image, background included.
"""
from __future__ import annotations

import torch
from torch import nn

from warpgs.train.extensions import Extension, register_extension


class ViewExposures(nn.Module):
    """One affine colour transform per training view: deltas from identity, re-centred to a mean of zero over the
    views at every use (the gauge above)."""

    def __init__(self, num_views: int):
        super().__init__()
        if num_views < 1:
            raise ValueError(f"exposure: expected at least one training view, got {num_views}")
        self.deltas = nn.Parameter(torch.zeros(num_views, 3, 4))

    def transforms(self) -> torch.Tensor:
        """[V, 3, 4]: identity plus each view's delta minus the mean delta."""
        eye = torch.eye(3, 4, device=self.deltas.device, dtype=self.deltas.dtype)
        return eye + self.deltas - self.deltas.mean(0, keepdim=True)

    def forward(self, rgb: torch.Tensor, row: int) -> torch.Tensor:
        a = self.transforms()[row]
        return rgb @ a[:, :3].T + a[:, 3]


@register_extension("exposure")
class Exposure(Extension):
    def __init__(self, lr: float = 0.001):
        self.lr = float(lr)
        if not self.lr > 0:
            raise ValueError(f"extensions.exposure.lr: expected a positive learning rate, got {lr!r}")
        self._rows = {}

    def setup(self, trainer) -> None:
        train = list(trainer.scene.train)
        self._rows = {index: row for row, index in enumerate(train)}
        trainer.add_module("exposure", ViewExposures(len(train)), lr=self.lr)

    def after_render(self, trainer, out, batch: dict, step: int):
        row = self._rows.get(batch.get("index", -1))
        if out.rgb is None or row is None or not torch.is_grad_enabled() or not _scene_camera(trainer, batch):
            return out
        out.rgb = trainer.modules["exposure"](out.rgb, row)
        return out


def _scene_camera(trainer, batch: dict) -> bool:
    """Whether the render is of the training view's own camera (at any scale), not a camera made from it (a virtual
    view keeps no index; this guards against one that would)."""
    view = batch.get("view")
    return view is not None and getattr(view, "name", None) == trainer.scene.cameras[batch["index"]].name
