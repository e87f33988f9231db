"""Losses: the registry and the built-in terms (importing this package registers them)."""
from warpgs.losses.registry import (
    DEFAULT_LOSSES,
    KNOWN_OUTPUTS,
    LossResult,
    LossTerm,
    Schedule,
    batch_field,
    compute_losses,
    get_loss,
    parse_schedule,
    register_loss,
    registered_losses,
    render_output,
    required_batch_fields,
    required_outputs,
    resolve_losses,
    unregister_loss,
)
from warpgs.losses import photometric  # noqa: F401  (registers "l1" and "dssim")
from warpgs.losses import marr  # noqa: F401  (registers "depth", "depth_grad", "depth_local")
from warpgs.losses import gestalt  # noqa: F401  (registers "opacity", "scale", "count")
from warpgs.losses import depth_patch  # noqa: F401  (registers "depth_patch", off unless a config lists it)
from warpgs.losses import continuity  # noqa: F401  (registers "depth_smooth", off unless a config lists it)

__all__ = [
    "DEFAULT_LOSSES", "KNOWN_OUTPUTS", "LossResult", "LossTerm", "Schedule", "batch_field", "compute_losses",
    "get_loss", "parse_schedule", "register_loss", "registered_losses", "render_output", "required_batch_fields",
    "required_outputs", "resolve_losses", "unregister_loss",
]
