"""A decorator for the backward of autograd Functions whose backward autograd cannot record (Warp kernels,
collectives): a second derivative through them (create_graph=True) is refused at once, by name. torch's
`once_differentiable` refuses it only when the incoming gradient itself needs a gradient, so a loss linear in the
output (a mean, an SSIM's final mean) would silently lose the function's second-order part. No Warp import here."""
from __future__ import annotations

import functools

import torch


def differentiable_once(what: str):
    """@staticmethod / @differentiable_once("the 3D render") above `backward`: raises when autograd runs the backward
    with grad mode on, which it does only for create_graph=True."""
    def decorate(backward):
        @functools.wraps(backward)
        def wrapper(ctx, *grads):
            if torch.is_grad_enabled():
                raise RuntimeError(f"{what}: its backward is not differentiable (Warp kernels or a collective); "
                                   f"create_graph=True through it (a second derivative, a gradient penalty) is not "
                                   f"supported")
            return backward(ctx, *grads)
        return wrapper
    return decorate
