"""Console entry points: warpgs-train / -render / -eval (commands.py), warpgs-demo, orbit camera paths.
`python -m warpgs.cli train|render|eval ...` runs the same commands."""
from warpgs._lazy import lazy_exports

_NAMES = {
    "train_main": "warpgs.cli.commands",
    "render_main": "warpgs.cli.commands",
    "eval_main": "warpgs.cli.commands",
    "main": "warpgs.cli.commands",
}
__all__ = list(_NAMES)
__getattr__, __dir__ = lazy_exports(globals(), _NAMES)
