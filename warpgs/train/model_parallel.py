"""Model-parallel training of 3D Gaussians, the pieces a trainer step needs (docs/distributed.md, "Model
parallelism"): each rank owns a contiguous shard of the primitives (parameters and optimizer state), renders
its own view of the step from every rank's primitives (`render_sharded`), and back-propagates; the gradients of
its shard arrive from every rank's view through the splat exchange, so no parameter gradient is all-reduced and
each rank's optimizer steps its own rows. `gather_model` puts the shards together for checkpoints, PLY files and
evaluation. The Trainer's `train.parallel=model` (train/sharded_step.py) is built on these: `shard_training`
after the whole model is built or resumed, `gathered_training` wherever the whole model is needed (checkpoints in
the single-process format, PLY files, evaluation)."""
from __future__ import annotations

import copy
import dataclasses
from typing import Optional, Sequence

import torch
import torch.distributed as dist

from warpgs.model.gaussians import GaussianModel
from warpgs.render.gaussians import RenderOutput
from warpgs.render.sharded import render_sharded
from warpgs.train.distributed import Ranks
from warpgs.train.optim import MOMENTS, fused_adam, move_parameters, update_rows  # "step": the same on every rank
from warpgs.train.densify_stats import DensifyStats


def shard_model(model: GaussianModel, ranks: Ranks) -> GaussianModel:
    """This rank's contiguous share of `model`'s primitives, as a model of its own (Ranks.shard: sizes differ by
    at most one). Every rank must pass the same model."""
    if model.kind != "gaussians":
        raise ValueError(f"model.kind={model.kind}: model-parallel rendering exists for 3D Gaussians only")
    rows = ranks.shard(model.num_primitives)
    state = model.to_dict()
    state["params"] = {name: t[rows] for name, t in state["params"].items()}
    return GaussianModel.from_dict(state, device=model.means.device)


def gather_model(shard: GaussianModel, ranks: Ranks, device=None) -> GaussianModel:
    """The whole model from every rank's shard (on every rank), for checkpoints, PLY files and evaluation; on
    `device` (default: the shard's; each gathered parameter goes there as soon as it arrives)."""
    state = shard.to_dict()
    device = shard.means.device if device is None else torch.device(device)
    state["params"] = {name: ranks.all_gather_rows(p.detach(), what=f"gathering the model's {name}").cpu()
                       for name, p in shard.params.items()}
    return GaussianModel.from_dict(state, device=device)


def render_shard(shard: GaussianModel, viewmats: torch.Tensor, Ks: torch.Tensor, width, height, *,
                 outputs: Sequence[str] = ("rgb", "alpha"), background: Optional[torch.Tensor] = None,
                 inputs: Optional[dict] = None, group: Optional[dist.ProcessGroup] = None,
                 track_means2d: bool = False, **options) -> RenderOutput:
    """This rank's camera (one of viewmats [R,4,4] / Ks [R,3,3], the same on every rank) from every rank's
    shard; differentiable into this rank's shard from every rank's loss. `inputs` (default: the shard's
    render_inputs) may carry features; `options` are render_sharded's (near, far, tile_size, alpha_min, ...)."""
    inputs = dict(shard.render_inputs() if inputs is None else inputs)
    return render_sharded(inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"], inputs["colors"],
                          viewmats, Ks, width, height, sh_degree=inputs.get("sh_degree"),
                          features=inputs.get("features"), background=background, outputs=outputs, group=group,
                          track_means2d=track_means2d, **options)


def require_gaussians(kind: str) -> None:
    """Model-parallel rendering exists for 3D Gaussians only (the splat exchange carries their projection)."""
    if kind != "gaussians":
        raise ValueError(f"train.parallel=model: model.kind={kind}; model-parallel rendering exists for 3D "
                         f"Gaussians only (use train.parallel=data)")


def shard_training(model: GaussianModel, optimizer: torch.optim.Optimizer, strategy, ranks: Ranks) -> slice:
    """Turn a whole model's training state into this rank's share, in place: its rows of the model (Ranks.shard),
    of the optimizer's moments and of the strategy's statistics; the strategy's budget becomes this rank's share of
    it. Every rank must hold the same whole state. Returns the rows kept."""
    require_gaussians(model.kind)
    rows = ranks.shard(model.num_primitives)
    keep = torch.arange(rows.start, rows.stop, device=model.means.device)
    update_rows(model, optimizer, keep=keep)
    strategy.stats = strategy.stats.map(lambda t: t[keep])
    # Losses that read the model (mean opacity, soft count, ...) sum over every rank's rows through this.
    model.reduce_rows = lambda t: ranks.all_reduce_differentiable(t, what="a loss's sum over the primitives")
    budget = strategy.config.max_primitives
    share = ranks.shard(budget)
    strategy.config = dataclasses.replace(strategy.config, max_primitives=share.stop - share.start)
    return rows


def move_training(model: GaussianModel, optimizer: torch.optim.Optimizer, strategy, device,
                  adam_kernel: str = "auto") -> None:
    """Put the model's parameters, their optimizer moments and the strategy's statistics on `device`, in place
    (a model-parallel rank's share, built in CPU memory, onto its GPU). The optimizer then takes the Adam kernel
    `adam_kernel` (optim.adam_kernel) picks for `device`: built over CPU tensors it chose foreach, and on a GPU
    "auto" means fused, as it does for a model built there."""
    device = torch.device(device)
    move_parameters(model, optimizer, device)
    strategy.stats = strategy.stats.map(lambda t: t.to(device))
    if fused_adam(adam_kernel, on_cuda=device.type == "cuda"):
        for group in optimizer.param_groups:
            group["fused"], group["foreach"] = True, None
        optimizer.defaults.update(fused=True, foreach=None)
        for state in optimizer.state.values():  # the fused kernel reads its step count on the device
            if torch.is_tensor(state.get("step")):
                state["step"] = state["step"].to(device, torch.float32)


def gathered_training(model: GaussianModel, optimizer: torch.optim.Optimizer, strategy, ranks: Ranks, *,
                      budget: int, device="cpu"):
    """(whole model, an optimizer over it with every rank's moments, a strategy with every rank's statistics and
    the whole `budget`), on every rank: the state a single process would hold, for a checkpoint that resumes on any
    number of processes (and in either parallel mode). A collective: every rank calls it. It is put together on
    `device`, by default the CPU, so that a model whose shards fill the GPUs can still be saved. The strategy's
    random generator is this rank's (rank 0's goes into a checkpoint)."""
    whole = gather_model(model, ranks, device)
    groups, state = [], {}
    for group in optimizer.param_groups:
        name, (mine,) = group["name"], group["params"]
        p = whole.params[name]
        groups.append({**{k: v for k, v in group.items() if k != "params"}, "params": [p]})
        local = optimizer.state.get(mine, {})
        state[p] = {k: v for k, v in local.items() if k not in MOMENTS}
        for key in MOMENTS:  # every rank gathers both, present or not, so the collectives line up
            rows = local[key] if key in local else torch.zeros_like(mine)
            state[p][key] = ranks.all_gather_rows(rows, what=f"gathering Adam's {key} of {name}").to(whole.device)
    whole_optimizer = type(optimizer)(groups, **optimizer.defaults)
    for p, st in state.items():
        if "step" in st:
            whole_optimizer.state[p] = st
    whole_strategy = copy.copy(strategy)
    whole_strategy.config = dataclasses.replace(strategy.config, max_primitives=int(budget))
    whole_strategy.stats = DensifyStats.of({key: ranks.all_gather_rows(t, what=f"gathering the {key}").to(whole.device)
                                            for key, t in strategy.stats.tensors().items()})
    return whole, whole_optimizer, whole_strategy
