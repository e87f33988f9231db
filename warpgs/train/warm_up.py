"""Compile the step's kernels before the training clock starts. Warp builds (or loads from its kernel cache) a
module the first time one of its kernels is launched, so without this the first timed steps of a run carry that
work: on a machine whose cache is cold, 8-10 s inside the first 1000 steps of a GPU run of bonsai800 (its later
thousands take about 5 s), and about 5 s on the 2-core CPU. gsplat's kernels are built when it is installed, so a
step clock that includes ours compares a cold cache against a warm one. The loop runs one training view's render,
loss and backward here, in its own stage (metrics.json "stage_seconds"), and drops what it leaves behind: the
gradients, and the random numbers it drew (the RNG state is restored), so the run trains exactly as it would have."""
from __future__ import annotations

import torch

from warpgs.train.step import speculative_pairs  # the step's rule, not a copy


def compile_step_kernels(trainer) -> None:
    """One render + loss + backward of the first training view at the current step, through the same calls a step
    makes (the extensions' inputs, the loss set, the densification statistics' means2d, the speculative pair
    sizing), then every gradient dropped. Primitive dropout and virtual views are torch ops on top of the same
    kernels, so they are left out."""
    if trainer.model_parallel or not trainer.views.indices or trainer.model.num_primitives == 0:
        return  # model-parallel steps render through their own sharded calls (train/sharded_step.py)
    step = trainer.step
    view = trainer.view(trainer.views.indices[0])
    devices = [trainer.device] if trainer.device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        batch = trainer.make_batch(view, step)
        out = trainer.render(view, trainer.outputs_at(step), batch, track_means2d=True, step=step,
                             speculative_pairs=speculative_pairs(trainer))
        result = trainer.loss_set(out, batch, trainer.model, step, trainer.max_steps)
        result.total.backward()
    for _, p in trainer.named_parameters():
        p.grad = None
    if trainer.device.type == "cuda":  # its kernels run inside this stage, not in the first step's time
        torch.cuda.synchronize(trainer.device)
