"""Compile the step's kernels before the training clock starts. Warp builds (or loads from its kernel cache) a
module the first time one of its kernels is launched, so without this the first timed steps of a run carry that
work: on a machine whose cache is cold, 8-10 s inside the first 1000 steps of a GPU run of bonsai800 (its later
thousands take about 5 s), and about 5 s on the 2-core CPU. gsplat's kernels are built when it is installed, so a
step clock that includes ours compares a cold cache against a warm one. The loop runs one training view's render,
loss and backward here, in its own stage (metrics.json "stage_seconds"), and drops what it leaves behind: the
gradients, and the random numbers it drew (the RNG state is restored), so the run trains exactly as it would have."""
from __future__ import annotations

import torch


def compile_step_kernels(trainer) -> None:
    """The step's own view pass (render, loss, backward: train/step.view_pass, through the trainer's method as
    train_step calls it) on the first training view at the current step, densifying, then every gradient dropped."""
    if trainer.model_parallel or not trainer.views.indices or trainer.model.num_primitives == 0:
        return  # model-parallel steps render through their own sharded calls (train/sharded_step.py)
    view = trainer.view(trainer.views.indices[0])
    devices = [trainer.device] if trainer.device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):  # primitive dropout draws random numbers
        trainer.view_pass(view, trainer.step, densify=True)
    for _, p in trainer.named_parameters():
        p.grad = None
    if trainer.device.type == "cuda":  # its kernels run inside this stage, not in the first step's time
        torch.cuda.synchronize(trainer.device)
