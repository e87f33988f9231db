"""Training: the Trainer and its collaborators (loop, checkpoints, evaluation, non-finite guard), the
densification strategy, optimizers, trainer extensions, and batches / data-parallel training (distributed.py)."""
from warpgs._lazy import lazy_exports

_NAMES = {
    "Trainer": "warpgs.train.trainer",
    "TrainResult": "warpgs.train.loop",
    "NonFiniteError": "warpgs.train.guard",
    "DistributedError": "warpgs.train.distributed",
    "Extension": "warpgs.train.extensions",
    "register_extension": "warpgs.train.extensions",
}
__all__ = list(_NAMES)
__getattr__, __dir__ = lazy_exports(globals(), _NAMES)
