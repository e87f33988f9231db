"""What adaptive density control counts between refines (train/strategy.py reads it at each refine): per primitive,
the summed norm of its screen-space gradient, the views it was visible in, and its largest screen radius.

A step's statistics travel as an "observations" dict ({"grad", "count", "radii", "screen"}, [N] each), so that
several cameras or ranks can be combined (`merge_observations`, or an all-reduce in train/distributed.py) before they
are added (`DensifyStats.add`).

Gradient units: as 3DGS (and gsplat), the accumulated statistic is the norm of the gradient with respect to NDC
coordinates, dL/dndc = dL/dpixel * (W/2, H/2), times B for a batch of B cameras (the loss is a mean over them),
averaged over the steps in which the primitive was visible. Radii are kept only when a screen-size rule reads them
(otherwise observations carry None and the maxima stay 0).
"""
from __future__ import annotations

from typing import Optional

import torch

STATISTICS = ("grad_accum", "count", "max_radii", "max_screen")  # DensifyStats's rows, one per primitive


@torch.no_grad()
def observations(grad2d: torch.Tensor, visible: torch.Tensor, radii: Optional[torch.Tensor], width: int,
                 height: int, views_in_loss: Optional[int] = None) -> dict:
    """grad2d [B,N,2] px, visible [B,N], radii [B,N] px -> {"grad": summed NDC gradient norms [N], "count": views in
    which each primitive was visible [N], "radii": largest radius px [N], "screen": the same as a fraction of the
    image's larger side [N]} (radii None: both None). views_in_loss: how many views the loss averages over
    (default B), the factor that turns the gradient of the mean back into each view's own."""
    batch = grad2d.shape[0] if views_in_loss is None else int(views_in_loss)
    # Python-scalar factors: a small tensor of them built here would be a host-to-device copy, which torch
    # follows with a stream sync (a GPU profile found one in every densifying step).
    g = grad2d.detach()
    norms = torch.hypot(g[..., 0] * (0.5 * width * batch), g[..., 1] * (0.5 * height * batch))
    vis = visible.to(torch.bool)
    out = {"grad": torch.where(vis, norms, torch.zeros_like(norms)).sum(0), "count": vis.sum(0),
           "radii": None, "screen": None}
    if radii is not None:  # None: no screen-size rule reads them (the default), so none are kept
        seen = torch.where(vis, radii, torch.zeros_like(radii)).amax(0)
        out.update(radii=seen, screen=seen / max(width, height))
    return out


def merge_observations(observed) -> dict:
    """Several cameras' observations as one: sums of "grad" and "count", maxima of "radii" and "screen"."""
    observed = list(observed)
    out = dict(observed[0])
    for obs in observed[1:]:
        out = {"grad": out["grad"] + obs["grad"], "count": out["count"] + obs["count"],
               "radii": _maximum(out["radii"], obs["radii"]), "screen": _maximum(out["screen"], obs["screen"])}
    return out


def _maximum(a: Optional[torch.Tensor], b: Optional[torch.Tensor]) -> Optional[torch.Tensor]:
    """Elementwise maximum of two observations' radii; None when neither camera computed them."""
    if a is None or b is None:
        return a if b is None else b
    return torch.maximum(a, b)


class DensifyStats:
    """The statistics of N primitives since the last refine: grad_accum (summed NDC gradient norms), count (views
    seen in), max_radii (px) and max_screen (fraction of the image's larger side), [N] each."""

    def __init__(self, n: int, device="cpu"):
        self.grad_accum = torch.zeros(n, device=device)
        self.count = torch.zeros(n, dtype=torch.int64, device=device)
        self.max_radii = torch.zeros(n, device=device)
        self.max_screen = torch.zeros(n, device=device)

    def __len__(self) -> int:
        return int(self.grad_accum.shape[0])

    @torch.no_grad()
    def add(self, obs: dict) -> None:
        """Add one step's observations (of one camera, merged cameras, or all ranks)."""
        self.grad_accum += obs["grad"]
        self.count += obs["count"]
        if obs["radii"] is not None:
            self.max_radii = torch.maximum(self.max_radii, obs["radii"])
            self.max_screen = torch.maximum(self.max_screen, obs["screen"])

    def average_grads(self) -> torch.Tensor:
        return self.grad_accum / self.count.clamp_min(1)

    def tensors(self) -> dict:
        return {key: getattr(self, key) for key in STATISTICS}

    @classmethod
    def of(cls, tensors: dict) -> "DensifyStats":
        """Statistics holding the given tensors (STATISTICS keys); a missing max_screen (checkpoints from before
        it) restarts at 0 until the next refine."""
        missing = [key for key in STATISTICS[:3] if tensors.get(key) is None]
        if missing:
            raise KeyError(f"densification statistics: {', '.join(missing)} missing (a strategy state from "
                           f"before initialize, or a damaged checkpoint)")
        stats = cls.__new__(cls)
        for key in STATISTICS:
            setattr(stats, key, tensors.get(key))
        if stats.max_screen is None:
            stats.max_screen = torch.zeros_like(stats.max_radii)
        return stats

    def map(self, fn) -> "DensifyStats":
        """New statistics with fn(tensor) of each (rows picked, moved to a device, gathered over ranks, ...)."""
        return DensifyStats.of({key: fn(t) for key, t in self.tensors().items()})
