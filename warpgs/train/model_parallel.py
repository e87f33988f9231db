"""Model-parallel training of 3D Gaussians, the pieces a trainer step needs (docs/distributed.md, "Model
parallelism"): each rank owns a contiguous shard of the primitives (parameters and optimizer state), renders
its own view of the step from every rank's primitives (`render_sharded`), and back-propagates; the gradients of
its shard arrive from every rank's view through the splat exchange, so no parameter gradient is all-reduced and
each rank's optimizer steps its own rows. `gather_model` puts the shards together for checkpoints, PLY files and
evaluation. Not yet wired into the Trainer (densification and checkpoints per owner are the next step)."""
from __future__ import annotations

from typing import Optional, Sequence

import torch
import torch.distributed as dist

from warpgs.model.gaussians import GaussianModel
from warpgs.render.gaussians import RenderOutput
from warpgs.render.sharded import render_sharded
from warpgs.train.distributed import Ranks


def shard_model(model: GaussianModel, ranks: Ranks) -> GaussianModel:
    """This rank's contiguous share of `model`'s primitives, as a model of its own (Ranks.shard: sizes differ by
    at most one). Every rank must pass the same model."""
    if model.kind != "gaussians":
        raise ValueError(f"model.kind={model.kind}: model-parallel rendering exists for 3D Gaussians only")
    rows = ranks.shard(model.num_primitives)
    state = model.to_dict()
    state["params"] = {name: t[rows] for name, t in state["params"].items()}
    return GaussianModel.from_dict(state, device=model.means.device)


def gather_model(shard: GaussianModel, ranks: Ranks) -> GaussianModel:
    """The whole model from every rank's shard (on every rank), for checkpoints, PLY files and evaluation."""
    state = shard.to_dict()
    device = shard.means.device
    state["params"] = {name: ranks.all_gather_rows(p.detach(), what=f"gathering the model's {name}").cpu()
                       for name, p in shard.params.items()}
    return GaussianModel.from_dict(state, device=device)


def render_shard(shard: GaussianModel, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, *,
                 outputs: Sequence[str] = ("rgb", "alpha"), background: Optional[torch.Tensor] = None,
                 near: float = 0.01, far: float = 1e10, group: Optional[dist.ProcessGroup] = None) -> RenderOutput:
    """This rank's camera (one of viewmats [R,4,4] / Ks [R,3,3], the same on every rank) from every rank's
    shard; differentiable into this rank's shard from every rank's loss."""
    inputs = shard.render_inputs()
    return render_sharded(inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"], inputs["colors"],
                          viewmats, Ks, width, height, sh_degree=inputs["sh_degree"], background=background,
                          outputs=outputs, near=near, far=far, group=group)

