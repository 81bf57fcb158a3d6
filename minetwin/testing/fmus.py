"""Load an FMU for a test and validate it against the interface an asset needs.

Wraps ``cosim.fmu.FmuComponent`` (which checks variables, causalities and
array sizes at load, fmus/README.md) with interface names a test can
write: a registered FMU role such as ``"crusher"`` or ``"mill"`` (fmus/README.md), or a tuple of
``cosim.fmu.VariableSpec`` for an asset of the user's own. A built FMU may
be named by its model name (``"cone_crusher"`` -> fmus/build/cone_crusher.fmu).
"""

from __future__ import annotations

from pathlib import Path

from cosim.errors import ValidationError


def interfaces() -> dict:
    """The registered FMU roles' interfaces (``cosim.fmu_registry``), by role."""
    from cosim.fmu_registry import registered_roles, role_interface

    return {role: role_interface(role) for role in registered_roles()}


def load_validated_fmu(path, interface="crusher", *, name=None, parameters=None):
    """An ``FmuComponent`` for ``path`` validated against ``interface``.

    Raises ``cosim.fmu.FmuInterfaceError`` naming the file, the variable and
    what was expected if the FMU does not offer what the asset needs.
    """
    from cosim.fmu import FmuComponent, fmu_path

    if isinstance(interface, str):
        known = interfaces()
        if interface not in known:
            raise ValidationError("interface", f"one of {sorted(known)} or a tuple of VariableSpec",
                                  f"got {interface!r}")
        interface = known[interface]
    text = str(path)
    path = Path(text) if text.endswith(".fmu") else fmu_path(text)
    return FmuComponent(path, interface=interface, name=name, parameters=parameters)
