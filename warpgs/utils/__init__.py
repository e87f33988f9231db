"""Small shared helpers: atomic file writes, the progress line."""
from warpgs._lazy import lazy_exports

_NAMES = {
    "atomic_write_bytes": "warpgs.utils.atomic_file",
}
__all__ = list(_NAMES)
__getattr__, __dir__ = lazy_exports(globals(), _NAMES)
