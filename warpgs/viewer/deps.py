"""The viewer's optional dependency: viser (web server + three.js client), from the `viewer` extra."""
from __future__ import annotations

INSTALL_HINT = "pip install 'warpgs[viewer]'"


class ViewerUnavailable(ImportError):
    """The `viewer` extra is not installed."""


def require_viser(who: str = "the viewer"):
    """The viser module, or ViewerUnavailable saying how to install it (`who` names the command or config key)."""
    try:
        import viser
    except ImportError as e:  # also a broken install (a dependency of viser missing)
        raise ViewerUnavailable(f"{who} needs the viewer extra: {INSTALL_HINT} ({e})") from e
    return viser
