"""Asset kinds: what a scenario may list under ``[assets.NAME]``, found through entry points.

A kind is a class with a ``Parameters`` model (``cosim.params``) and a
``build`` method; it is registered in the ``minetwin.assets`` entry-point
group of its package's metadata, the built-in kinds (pyproject.toml) exactly
as a third-party package's::

    [project.entry-points."minetwin.assets"]
    apron_feeder = "my_plant.feeder:ApronFeederKind"

``asset_kind(name)`` loads the one a scenario names; ``asset_kinds()`` lists
them all. A kind implements one method (ASE-calculator style), the base class
does the rest:

``build(name, parameters, context)``
    create the asset's components, ``context.add`` each (in stepping order)
    and ``context.connect`` their internal signals (an FMU's); return the
    components that own the asset's ports (flows attach to them; a truck fleet
    returns its trucks).

Optional: ``ports(parameters)`` (default: the class attributes ``inlets``
and ``outlets`` of ``component``), ``location(parameters, inlet)`` (where an
inlet is [m], for the assets that feed it: a truck drives to it), and
``check(name, parameters, plant)`` (references to other assets: a list of
``ValidationError``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from cosim.errors import ValidationError
from cosim.plugins import registered

ENTRY_POINT_GROUP = "minetwin.assets"


class AssetKind:
    """Base class of the asset kinds; subclasses set ``Parameters`` and ``build``."""

    Parameters: type = None
    """The kind's parameter table (a ``cosim.params.Parameters`` model)."""
    component: type = None
    """The class of the component that owns the ports (for the default ``ports``)."""
    loadable = False
    """True for kinds that trucks load from (``take(mass, t)``), as a source."""
    fmu_role: str | None = None
    """The FMU role (``cosim.fmu_registry``) of the kind's FMU, if it steps one: its
    interface is checked when the FMU loads."""

    def ports(self, parameters) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """``(inlets, outlets)`` of an asset of this kind with ``parameters``."""
        return tuple(self.component.inlets), tuple(self.component.outlets)

    def location(self, parameters, inlet: str) -> list[float]:
        """Where ``inlet`` is [m] (default: the table's ``position_m``)."""
        return list(parameters.position_m)

    def check(self, name: str, parameters, plant: "PlantSpec") -> list[ValidationError]:
        """Errors in what the asset says about others (default: none)."""
        return []

    def build(self, name: str, parameters, context: "BuildContext") -> list:
        raise NotImplementedError


@dataclass
class PlantSpec:
    """A validated plant: assets (name -> (kind, parameters)) in order, and the flows."""

    assets: dict = field(default_factory=dict)
    flows: list = field(default_factory=list)
    kind_names: dict = field(default_factory=dict)
    """Asset name -> the name of its kind in the registry."""

    def feeds(self, name: str, outlet: str) -> list[tuple[str, str]]:
        """``(asset, inlet)`` of every flow out of ``name.outlet``."""
        return [(flow["to_asset"], flow["to_port"]) for flow in self.flows
                if flow["from_asset"] == name and flow["from_port"] == outlet]


@dataclass
class BuildContext:
    """What a kind's ``build`` gets besides its parameters."""

    plant: object
    """The shared ``cosim.assets.Plant`` (particle store, events, generator)."""
    master: object
    """The ``cosim.master.Master``; use ``add`` and ``connect`` below."""
    simulation: dict
    """The scenario's ``[simulation]`` table (seed, sensor_window_s, record_every_s, ...)."""
    spec: PlantSpec
    built: dict = field(default_factory=dict)
    """Port components of the assets built so far, by asset name."""

    def add(self, component):
        return self.master.add(component)

    def connect(self, source, output: str, target, input: str) -> None:
        self.master.connect(source, output, target, input)

    def inlet_location(self, name: str, outlet: str) -> list[float]:
        """Where the flow out of ``name.outlet`` arrives [m] (its first target inlet)."""
        target, inlet = self.spec.feeds(name, outlet)[0]
        kind, parameters = self.spec.assets[target]
        return kind.location(parameters, inlet)


_KINDS: dict[str, object] | None = None


def _entry_points() -> dict[str, object]:
    global _KINDS
    if _KINDS is None:
        _KINDS = registered(ENTRY_POINT_GROUP)
    return _KINDS


def asset_kinds() -> list[str]:
    """Names of the registered asset kinds."""
    return sorted(_entry_points())


def asset_kind(name: str, field: str = "kind") -> AssetKind:
    """The registered asset kind ``name`` (an instance), or a ``ValidationError``."""
    point = _entry_points().get(name)
    if point is None:
        raise ValidationError(field, f"one of {asset_kinds()} (entry points "
                              f"{ENTRY_POINT_GROUP!r})", f"got {name!r}")
    return point.load()()
