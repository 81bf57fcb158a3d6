"""What installed packages register through entry points (``importlib.metadata``).

One lookup for every registry of the framework: asset kinds (``minetwin.assets``),
storage models (``minetwin.storage``), fidelity cards (``minetwin.fidelity``), FMU
roles and FMU files (``minetwin.fmu_roles``, ``minetwin.fmus``).
"""

from __future__ import annotations

from importlib.metadata import entry_points

from cosim.errors import ValidationError


def registered(group: str) -> dict:
    """The entry points of ``group``: name -> entry point (not yet imported), by name."""
    return {ep.name: ep for ep in sorted(entry_points(group=group), key=lambda ep: ep.name)}


def load_registered(point, field: str, what: str):
    """The object ``point`` names, imported now; a plug-in that fails to import is a
    ``ValidationError`` on ``field`` naming it and why (``what`` it should be)."""
    try:
        return point.load()
    except Exception as exc:  # a broken plug-in is reported, not raised through
        raise ValidationError(field, f"{what} that imports ({point.value})",
                              f"{point.name!r} failed: {type(exc).__name__}: {exc}") from None
