"""viser is optional (extra ``[viewer]``): import it only when a viewer is made."""

from __future__ import annotations

from types import ModuleType


class ViewerNotInstalledError(ImportError):
    """The viewer needs viser, which is not installed."""


def require_viser() -> ModuleType:
    """Import viser, or raise :class:`ViewerNotInstalledError` naming the extra to install."""
    try:
        import viser
    except ImportError as exc:
        from ndtom_ti.extras import install_hint

        raise ViewerNotInstalledError(
            f"the map viewer needs the optional package viser, which is not installed "
            f"({exc}); install it with: {install_hint('viewer')}"
        ) from None
    return viser
