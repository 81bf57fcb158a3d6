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

from cosim.assets import Asset, Plant


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
    crusher : Asset
        Where the loads are dumped (``crusher.receive(ids, t)``).
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

    def __init__(self, name: str, plant: Plant, *, route, crusher, payload: float = 15000.0,
                 speed: float = 8.0, load_time: float = 6.0, dump_time: float = 2.75,
                 start: float = 0.0):
        first = route[0].location
        super().__init__(name, plant, location=first)
        self.route = list(route)
        self.crusher = crusher
        self.payload = float(payload)
        self.speed = float(speed)
        dump_point = np.asarray(crusher.location, dtype=float)
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

    @property
    def cycle_time(self) -> float:
        """Time for one pass over the route [s]."""
        return float(sum(stage.duration for stage in self._stages))

    def step(self, t: float, dt: float) -> None:
        t_end = t + dt
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
            self.crusher.receive(ids, t)
            self.dumps += 1

    def outputs(self) -> dict[str, float]:
        return {"x": float(self._position[0]), "y": float(self._position[1]),
                "payload_kg": float(self.particles.mass[self.particles.slots(self._held)].sum())
                if self._held.size else 0.0,
                "loads": float(self.loads)}
