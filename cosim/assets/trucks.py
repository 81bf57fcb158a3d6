"""Haul trucks: kinematic vehicles that carry loads from the sources to the crusher.

Source: paper section "Simulator": "Each haul truck receive a load of
roughly 15 ton (roughly 150 pseudo-particles) at the loading point. For
simplicity, the loading equipment is not modeled explicitly. The trucks dump
the load on the crusher inlet"; section "Results", "Step response": the
trucks dump alternately material from the left and right source with a 55 s
period. Section "Digital twin as a distributed particle simulation": "For a
bucket excavator or truck asset, the micro-tracking can be accomplished
simply by inheriting the position of the bucket or the truck".

Model (kinematic, no dynamics). A truck repeats its route: for each source
in ``route``: drive to the source's loading point, load for ``load_time``
[s], drive to the crusher, dump for ``dump_time`` [s]. Legs are straight
lines at constant ``speed`` [m/s]. The stage clock is exact (stage ends are
kept as real times and carried over between communication steps), so the
cycle period is exact on average even when stage ends fall between steps:
with 75 m legs at 8 m/s, 6 s loading and 2.75 s dumping the two-source
cycle is 4 * 9.375 + 2 * 6 + 2 * 2.75 = 55 s, the paper's period.

Particles co-move with their truck (micro-tracking): every step, the
particles a truck holds take the truck's position. Events: "appear" (by
the source) and "load" at the end of loading; "dump" when the load is handed
to the crusher at the end of dumping.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import model_validator

from cosim.assets import Asset, Plant
from cosim.errors import ValidationError
from cosim.kinds import AssetKind
from cosim.params import Parameters, Text, number, refuse

MAX_PARTICLES_PER_LOAD = 100_000
"""Most pseudo-particles in one truckload (payload_kg / particle_mass_kg; paper: ~150)."""


@dataclass
class _Stage:
    kind: str            # "wait", "drive", "load", "dump"
    duration: float      # [s]
    start: np.ndarray    # position at stage start [m]
    end: np.ndarray      # position at stage end [m]
    source: object = None


class HaulTruck(Asset):
    """One haul truck on a fixed route between sources and the crusher.

    Parameters
    ----------
    name : str
        Truck name.
    plant : Plant
        The shared plant.
    route : list of Source
        Sources visited in turn (the paper: left, right).
    dump_point : (3,) array_like
        Where the loads are dumped [m]: the inlet its outlet ``dump`` flows to
        (the crusher's hopper).
    payload : float
        Load per trip [kg] (paper: about 15 t).
    speed : float
        Driving speed [m/s].
    load_time, dump_time : float
        Time at the loading point and at the crusher [s].
    start : float
        Time the first loading starts [s]; until then the truck waits empty
        at its first source.
    """

    inlets = ()
    outlets = ("dump",)
    limits_step = True
    output_names = ("x", "y", "payload_kg", "loads")

    def __init__(self, name: str, plant: Plant, *, route, dump_point, payload: float = 15000.0,
                 speed: float = 8.0, load_time: float = 6.0, dump_time: float = 2.75,
                 start: float = 0.0):
        first = route[0].location
        super().__init__(name, plant, location=first)
        self.route = list(route)
        self.payload = float(payload)
        self.speed = float(speed)
        dump_point = np.asarray(dump_point, dtype=float)
        self._stages: list[_Stage] = []
        previous = dump_point
        for source in self.route:
            loading = np.asarray(source.location, dtype=float)
            self._stages += [
                _Stage("drive", math.dist(loading, previous) / self.speed, previous, loading),
                _Stage("load", float(load_time), loading, loading, source),
                _Stage("drive", math.dist(dump_point, loading) / self.speed, loading,
                       dump_point),
                _Stage("dump", float(dump_time), dump_point, dump_point),
            ]
            previous = dump_point
        # The first drive (from the crusher to the first source) is replaced
        # by waiting at the first source until ``start``.
        self._index = 1
        self._stage_end = float(start) + self._stages[1].duration
        self._position = np.asarray(first, dtype=float).copy()
        self._held = np.empty(0, dtype=np.uint64)
        self.loads = 0
        self.dumps = 0
        self._time = None  # end of the last step [s]

    @property
    def cycle_time(self) -> float:
        """Time for one pass over the route [s]."""
        return float(sum(stage.duration for stage in self._stages))

    def step_limit(self) -> float:
        """Time [s] from the end of the last step to the end of the next dump (an
        adaptive master's steps then shrink towards it, so a load reaches the crusher
        in a short step, not at the start of a long one); no limit before a step."""
        if self._time is None:
            return np.inf
        end, index = self._stage_end, self._index
        for _ in range(len(self._stages)):
            if self._stages[index].kind == "dump":
                return max(end - self._time, 0.0)
            index = (index + 1) % len(self._stages)
            end += self._stages[index].duration
        return np.inf

    def step(self, t: float, dt: float) -> None:
        t_end = t + dt
        self._time = t_end
        while self._stage_end <= t_end:
            self._finish_stage(self._stages[self._index], self._stage_end)
            self._index = (self._index + 1) % len(self._stages)
            self._stage_end += self._stages[self._index].duration
        stage = self._stages[self._index]
        started = self._stage_end - stage.duration
        if t_end < started:          # waiting for the first load
            fraction = 0.0
        else:
            fraction = (t_end - started) / stage.duration if stage.duration > 0 else 1.0
        self._position = stage.start + fraction * (stage.end - stage.start)
        if self._held.size:
            slots = self.particles.slots(self._held)
            self.particles.position[slots] = self._position

    def _finish_stage(self, stage: _Stage, t: float) -> None:
        if stage.kind == "load":
            ids = stage.source.take(self.payload, t)
            slots = self.particles.slots(ids)
            self.particles.set_owner(slots, self.owner, t)
            self.particles.position[slots] = stage.end
            self.plant.record("load", self.name, t, slots, stage.end)
            self._held = ids
            self.loads += 1
        elif stage.kind == "dump" and self._held.size:
            slots = self.particles.slots(self._held)
            self.plant.record("dump", self.name, t, slots, stage.end)
            ids, self._held = self._held, np.empty(0, dtype=np.uint64)
            self.send("dump", ids, t)
            self.dumps += 1

    def outputs(self) -> dict[str, float]:
        return {"x": float(self._position[0]), "y": float(self._position[1]),
                "payload_kg": float(self.particles.mass[self.particles.slots(self._held)].sum())
                if self._held.size else 0.0,
                "loads": float(self.loads)}


# ------------------------------------------------------------------ scenario kind
class TruckParameters(Parameters):
    """One truck of a fleet: see ``HaulTruck``."""

    name: Text | None = None
    """Component and event name (default ``<fleet>_<k>``, 1-based)."""
    route: list[Text]
    """Source assets visited in turn (declared before the fleet)."""
    payload_kg: number(0.0, 1e6, low_open=True, unit="kg") = 15000.0
    speed_m_s: number(0.0, 50.0, low_open=True, unit="m/s") = 8.0
    load_time_s: number(0.0, 3600.0, low_open=True, unit="s") = 6.0
    dump_time_s: number(0.0, 3600.0, low_open=True, unit="s") = 2.75
    start_s: number(0.0, 1e7, unit="s") = 0.0

    @model_validator(mode="after")
    def _route_given(self):
        if not self.route:
            raise refuse("route", "a non-empty list of source names", "got []")
        return self


class TruckFleetParameters(Parameters):
    """``[assets.NAME] kind = "truck_fleet"``: its trucks (``[[assets.NAME.trucks]]``)."""

    trucks: list[TruckParameters]

    @model_validator(mode="after")
    def _named(self):
        if not self.trucks:
            raise refuse("trucks", "a non-empty array of [[trucks]] tables", "got []")
        return self


class TruckFleetKind(AssetKind):
    """Haul trucks (``HaulTruck``), each on its route; outlet ``dump`` (the loads), which
    must flow to one inlet: the trucks drive to where that inlet is."""

    Parameters = TruckFleetParameters
    component = HaulTruck

    @staticmethod
    def names(name: str, parameters) -> list[str]:
        return [truck.name or f"{name}_{k + 1}" for k, truck in enumerate(parameters.trucks)]

    def check(self, name, parameters, plant):
        errors = []
        names = self.names(name, parameters)
        if len(set(names)) != len(names):
            errors.append(ValidationError(f"assets.{name}.trucks.name", "unique",
                                          f"got {names}"))
        declared = list(plant.assets)
        before = declared[:declared.index(name)]
        sources = [n for n in before if plant.assets[n][0].loadable]
        for k, truck in enumerate(parameters.trucks):
            path = f"assets.{name}.trucks[{k}]"
            if any(r not in sources for r in truck.route):
                errors.append(ValidationError(
                    f"{path}.route", f"a non-empty list of source names among {sources} "
                    "(sources declared before the fleet)", f"got {truck.route!r}"))
                continue
            lightest = truck.payload_kg / MAX_PARTICLES_PER_LOAD
            for source in truck.route:
                mass = plant.assets[source][1].particle_mass_kg
                if mass < lightest:
                    errors.append(ValidationError(
                        f"assets.{source}.particle_mass_kg",
                        f">= {lightest:g} kg ({path}.payload_kg / "
                        f"{MAX_PARTICLES_PER_LOAD:,} particles per load)", f"got {mass!r}"))
        if len(plant.feeds(name, "dump")) != 1:
            errors.append(ValidationError("flows", f"one flow from {name}.dump (where the "
                                          "trucks dump)",
                                          f"got {len(plant.feeds(name, 'dump'))}"))
        return errors

    def build(self, name, p, context):
        dump_point = context.inlet_location(name, "dump")
        trucks = []
        for truck_name, t in zip(self.names(name, p), p.trucks):
            truck = HaulTruck(truck_name, context.plant,
                              route=[context.built[r][0] for r in t.route],
                              dump_point=dump_point, payload=t.payload_kg, speed=t.speed_m_s,
                              load_time=t.load_time_s, dump_time=t.dump_time_s,
                              start=t.start_s)
            context.add(truck)
            trucks.append(truck)
        return trucks
