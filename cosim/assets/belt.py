"""Belt conveyor: particles co-move with bins of the belt.

Source: paper section "Digital twin as a distributed particle simulation":
"Particles transported on a belt conveyor may similarly be tracked between
the loading and discharge points by simply tracking the movement of the
belt using the conveyor control system. In the transporter's virtual asset,
the belt is discretized longitudinally in bins of known location and
particle content."

Model (kinematic). The belt has length L [m], bin length b [m] and speed
v(t) [m/s] (input ``speed``; input ``running`` 0 stops it, e.g. when the
stockpile is full). The belt's travel s(t) = integral of v dt [m] is the
tape coordinate; bin j covers tape [j b, (j + 1) b). A particle loaded at
travel s_0 joins the bin at the loading point, j = floor(s_0 / b), and its
distance from the loading point is s(t) - j b; the whole bin is discharged
when that distance reaches L. Particles take the position of their bin
along the straight line from ``start`` to ``end`` (micro-tracking).

Events: "enter" at loading, "exit" at discharge (asset = belt name).
"""

from __future__ import annotations

import math

import numpy as np

from cosim.assets import Asset, Plant
from cosim.errors import ValidationError


class BeltConveyor(Asset):
    """Straight belt conveyor discretised in bins.

    Parameters
    ----------
    name : str
        Asset name.
    plant : Plant
        The shared plant.
    start, end : (3,) array_like
        Loading and discharge points [m]; the length is their distance
        unless ``length`` is given.
    speed : float
        Belt speed [m/s] (default 2.0); the ``speed`` input overrides it.
    bin_length : float
        Bin length [m] (default 1.0).
    downstream : Asset
        Receives the discharged particles.
    """

    input_names = ("speed", "running")

    def __init__(self, name: str, plant: Plant, *, start, end, downstream,
                 speed: float = 2.0, bin_length: float = 1.0, length: float | None = None):
        super().__init__(name, plant, location=start)
        self.start = np.asarray(start, dtype=float)
        self.end = np.asarray(end, dtype=float)
        self.length = float(math.dist(self.end, self.start) if length is None else length)
        if not self.length > 0:
            raise ValidationError(f"{name}.length", "> 0 m", f"got {self.length!r}")
        if not bin_length > 0:
            raise ValidationError(f"{name}.bin_length", "> 0 m", f"got {bin_length!r}")
        self.speed = float(speed)
        self.bin_length = float(bin_length)
        self.downstream = downstream
        self._direction = (self.end - self.start) / max(math.dist(self.end, self.start),
                                                        1e-12)
        self._travel = 0.0
        self._ids = np.empty(0, dtype=np.uint64)
        self._bin_start = np.empty(0)        # tape coordinate of each particle's bin [m]
        self._mass_kg = 0.0
        self._delivered_kg = 0.0

    def _accept(self, ids: np.ndarray, t: float) -> None:
        bin_start = np.floor(self._travel / self.bin_length) * self.bin_length
        self._ids = np.concatenate((self._ids, ids))
        self._bin_start = np.concatenate((self._bin_start, np.full(ids.size, bin_start)))

    def step(self, t: float, dt: float) -> None:
        speed = float(self.inputs.get("speed", self.speed))
        running = float(self.inputs.get("running", 1.0)) > 0.5
        if running:
            self._travel += speed * dt
        if self._ids.size == 0:
            self._mass_kg = 0.0
            return
        store = self.particles
        distance = self._travel - self._bin_start
        # bins are loaded in order, so the discharged ones are a prefix
        count = int(np.searchsorted(-distance, -self.length, side="right"))
        slots = store.slots(self._ids)
        if count:
            leaving, self._ids = self._ids[:count], self._ids[count:]
            out_slots, slots = slots[:count], slots[count:]
            distance = distance[count:]
            self._bin_start = self._bin_start[count:]
            store.position[out_slots] = self.end
            self._delivered_kg += float(store.mass[out_slots].sum())
            self.plant.record("exit", self.name, t + dt, out_slots, tuple(self.end))
            self.downstream.receive(leaving, t + dt)
        store.position[slots] = self.start + distance[:, None] * self._direction
        self._mass_kg = float(store.mass[slots].sum())

    def outputs(self) -> dict[str, float]:
        return {"mass_kg": self._mass_kg, "delivered_kg": self._delivered_kg,
                "running": 1.0 if float(self.inputs.get("running", 1.0)) > 0.5 else 0.0}
