"""FMU roles and FMU files that packages register through entry points.

An asset kind that steps an FMU declares its **role** (``fmu_role = "crusher"``); the
role names the interface (a tuple of ``cosim.fmu.VariableSpec``) every FMU in that
role must offer, checked when the FMU is loaded (fmus/README.md, "Crusher" and
"Mill"). A package adds a role, or ships an FMU a scenario may name, in its own
``pyproject.toml``::

    [project.entry-points."minetwin.fmu_roles"]
    pebble_crusher = "my_package.interfaces:PEBBLE_CRUSHER_INTERFACE"

    [project.entry-points."minetwin.fmus"]
    my_jaw = "my_package:MY_JAW_FMU"        # a str or Path to the .fmu file

MineTwin registers its own roles (``crusher``, ``mill``) the same way. A scenario's
``fmu = "my_jaw"`` then resolves to the package's file (``cosim.fmu.resolve_fmu``):
a built FMU of that name (fmus/build) comes first.
"""

from __future__ import annotations

from pathlib import Path

from cosim.errors import ValidationError
from cosim.plugins import load_registered, registered

ROLE_ENTRY_POINT_GROUP = "minetwin.fmu_roles"
"""Entry-point group of the FMU roles: name = ``"module:INTERFACE"``."""
FMU_ENTRY_POINT_GROUP = "minetwin.fmus"
"""Entry-point group of the FMU files packages ship: name = ``"module:PATH"``."""


def registered_roles() -> list[str]:
    """The names of the registered FMU roles, sorted."""
    return list(registered(ROLE_ENTRY_POINT_GROUP))


def role_interface(role: str, field: str = "fmu_role") -> tuple:
    """The interface (tuple of ``VariableSpec``) an FMU in ``role`` must offer."""
    from cosim.fmu import VariableSpec

    points = registered(ROLE_ENTRY_POINT_GROUP)
    if role not in points:
        raise ValidationError(field, f"one of {list(points)} (the registered FMU roles)",
                              f"got {role!r}")
    interface = load_registered(points[role], field, "an FMU role")
    if not (isinstance(interface, tuple) and interface
            and all(isinstance(spec, VariableSpec) for spec in interface)):
        raise ValidationError(field, "a non-empty tuple of cosim.fmu.VariableSpec",
                              f"{role!r} is registered as {points[role].value}")
    return interface


def registered_fmus() -> list[str]:
    """The names of the FMU files packages registered, sorted."""
    return list(registered(FMU_ENTRY_POINT_GROUP))


def registered_fmu_path(name: str, field: str = "fmu") -> Path | None:
    """The file a package registered as FMU ``name`` (None if none did)."""
    point = registered(FMU_ENTRY_POINT_GROUP).get(name)
    if point is None:
        return None
    path = load_registered(point, field, "a registered FMU")
    if not isinstance(path, (str, Path)) or not Path(path).is_file():
        raise ValidationError(field, "a registered FMU whose .fmu file exists",
                              f"{name!r} ({point.value}) points to {path!r}")
    return Path(path)
