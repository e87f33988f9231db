"""Input checks for the render ops: every problem becomes a ValueError that names the argument."""
from __future__ import annotations

import torch


def check_tensor(name: str, t, shape: tuple, *, floating: bool = True) -> None:
    """`shape` uses None for a free dimension and an int for a fixed one."""
    if not isinstance(t, torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    if floating and t.dtype != torch.float32:
        raise ValueError(f"{name}: expected dtype float32, got {t.dtype} (convert with .float())")
    got = t.shape
    if len(got) == len(shape):  # a plain loop: every render call checks a dozen shapes
        for g, want in zip(got, shape):
            if want is not None and g != want:
                break
        else:
            return
    want = "[" + ", ".join("*" if d is None else str(d) for d in shape) + "]"
    raise ValueError(f"{name}: expected shape {want}, got {list(t.shape)}")


def check_same_device(named: dict) -> torch.device:
    devices = {name: t.device for name, t in named.items() if t is not None}
    first = next(iter(devices.values()))
    odd = [f"{n} on {d}" for n, d in devices.items() if d != first]
    if odd:
        raise ValueError(f"all tensors must be on one device; {next(iter(devices))} is on {first} but " + ", ".join(odd))
    return first


# The arrays the finite-value checks name, in the order they are reported (the first bad one is named), and the
# flag slots of kernels/input_checks.flag_bad_inputs (the last slot: an opacity outside [0, 1]).
CHECKED_NAMES = ("means", "quats", "scales", "opacities", "colors", "features", "viewmat", "K", "background")
OPACITY_RANGE_ERROR = "opacities must lie in [0, 1] (pass sigmoid(logits), not logits)"


def nonfinite_error(name: str) -> ValueError:
    return ValueError(f"{name} contains NaN or Inf values")


def check_finite(named: dict, opacities: torch.Tensor) -> None:
    """One host sync for all checks: finiteness of every tensor and opacities within [0, 1]. (GPU renders of 3D
    Gaussians flag these in a kernel instead, read at the pipeline's own sync: `raise_flagged`.)"""
    tensors = [t for t in named.values() if t is not None]
    flags = [torch.isfinite(t).all() for t in tensors]
    if opacities.numel():
        flags.append(((opacities >= 0) & (opacities <= 1)).all())
    ok = torch.stack(flags).cpu() if flags else torch.ones(0, dtype=torch.bool)
    if bool(ok.all()):
        return
    for (name, t), good in zip([(n, t) for n, t in named.items() if t is not None], ok):
        if not good:
            raise nonfinite_error(name)
    raise ValueError(OPACITY_RANGE_ERROR)


def raise_flagged(flags) -> None:
    """Raises check_finite's error from the flags of kernels/input_checks.flag_bad_inputs (one per CHECKED_NAMES,
    then the opacity range); returns when none is set."""
    if not any(flags):
        return
    for name, flag in zip(CHECKED_NAMES, flags):
        if flag:
            raise nonfinite_error(name)
    raise ValueError(OPACITY_RANGE_ERROR)


def named_inputs(means, quats, scales, opacities, colors, features, viewmat, K, background) -> dict:
    """The tensors the finite-value checks look at, by the names their errors give (validation.CHECKED_NAMES)."""
    return {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors,
            "features": features, "viewmat": viewmat, "K": K, "background": background}


# Device types whose renders run the finite-value checks inside the pipeline (GPUs: no host sync of their own).
# The CPU keeps the torch checks (a sync costs nothing there); tests add "cpu" to run the kernel's checks.
PIPELINE_CHECK_DEVICES = {"cuda"}


def checks_before_render(check_inputs: bool, pipeline_checks: bool, means, quats, scales, opacities, colors, features,
                         viewmat, K, background) -> bool:
    """Both ops' finite-value checks: run here (one host sync) when the render's pipeline cannot run them, else
    left to it (a kernel's flags, raised at the sync it makes anyway). Returns whether the pipeline must check
    (check_inputs, or `pipeline_checks`: a batched call asking each camera's render to)."""
    in_pipeline = value_checks_in_pipeline(means)
    if check_inputs and not in_pipeline:
        check_finite(named_inputs(means, quats, scales, opacities, colors, features, viewmat, K, background),
                     opacities)
    return (check_inputs or pipeline_checks) and in_pipeline


def value_checks_in_pipeline(means: torch.Tensor) -> bool:
    """Whether a render of `means` runs its finite-value checks in the fast pipeline (a kernel's flags, read with
    the tile-pair count) rather than in torch before it."""
    return means.device.type in PIPELINE_CHECK_DEVICES and means.shape[0] > 0
