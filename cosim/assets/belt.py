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

import numba
import numpy as np
from pydantic import model_validator

from cosim.assets import Asset, Plant
from cosim.errors import ValidationError
from cosim.kinds import AssetKind
from cosim.params import MAX_BLOCKS, MAX_LENGTH_M, Parameters, Position, number, refuse


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
    Particles enter at inlet ``feed`` (several flows into it merge on the
    belt) and leave at outlet ``out`` (several flows out of it split by mass).
    """

    input_names = ("speed", "running")
    output_names = ("mass_kg", "delivered_kg", "running")

    def __init__(self, name: str, plant: Plant, *, start, end,
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
        self._direction = (self.end - self.start) / max(math.dist(self.end, self.start),
                                                        1e-12)
        self._end_location = tuple(float(c) for c in self.end)
        self._travel = 0.0
        self._ids = np.empty(0, dtype=np.uint64)
        self._bin_start = np.empty(0)        # tape coordinate of each particle's bin [m]
        self._mass_kg = 0.0
        self._delivered_kg = 0.0

    def _accept(self, ids: np.ndarray, t: float, inlet: str) -> None:
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
        slots = store.slots(self._ids)
        # one compiled pass: the discharged bins (a prefix: bins are loaded in order) go
        # to the end, the others to their place along the belt
        count = _move_along(self._travel, self._bin_start, self.length, self.start,
                            self._direction, self.end, slots, store.position)
        if count:
            leaving, self._ids = self._ids[:count], self._ids[count:]
            out_slots, slots = slots[:count], slots[count:]
            self._bin_start = self._bin_start[count:]
            self._delivered_kg += float(store.mass[out_slots].sum())
            self.plant.record("exit", self.name, t + dt, out_slots, self._end_location)
            self.send("out", leaving, t + dt)
        self._mass_kg = float(store.mass[slots].sum())

    def outputs(self) -> dict[str, float]:
        return {"mass_kg": self._mass_kg, "delivered_kg": self._delivered_kg,
                "running": 1.0 if float(self.inputs.get("running", 1.0)) > 0.5 else 0.0}


@numba.njit(cache=True)
def _move_along(travel, bin_start, length, start, direction, end, slots, position) -> int:
    """Place the belt's particles (``slots``, in loading order, each in the bin starting
    at ``bin_start`` [m] of tape) at travel ``travel`` [m]: those whose bin has gone
    ``length`` or more at ``end``, the others at start + (travel - bin_start) direction.
    Returns how many reached the end (a prefix)."""
    count = 0
    while count < slots.size and travel - bin_start[count] >= length:
        count += 1
    for i in range(slots.size):
        slot = slots[i]
        if i < count:
            for k in range(3):
                position[slot, k] = end[k]
        else:
            distance = travel - bin_start[i]
            for k in range(3):
                position[slot, k] = start[k] + distance * direction[k]
    return count


# ------------------------------------------------------------------ scenario kind
class BeltParameters(Parameters):
    """``[assets.NAME] kind = "belt"``: see ``BeltConveyor``."""

    start_m: Position
    """Loading point [m]."""
    end_m: Position
    """Discharge point [m]."""
    length_m: number(0.0, MAX_LENGTH_M, low_open=True, unit="m") | None = None
    """Belt length [m] (default: the distance from start to end)."""
    speed_m_s: number(0.0, 20.0, unit="m/s") = 2.0
    bin_length_m: number(0.0, MAX_LENGTH_M, low_open=True, unit="m") | None = None
    """[m]; default: 1 m or the length if shorter."""

    @model_validator(mode="after")
    def _complete(self):
        if self.length_m is None:
            self.length_m = math.dist(self.start_m, self.end_m)
            if not self.length_m > 0:
                raise refuse("length_m", "> 0 m (give it, or a start away from the end)",
                             "start_m == end_m")
        if self.bin_length_m is None:
            self.bin_length_m = min(1.0, self.length_m)
        low = self.length_m / MAX_BLOCKS
        if not low <= self.bin_length_m <= self.length_m:
            raise refuse("bin_length_m", f"finite and >= {low:g} and <= {self.length_m:g} m",
                         f"got {self.bin_length_m!r}")
        return self


class BeltKind(AssetKind):
    """A belt conveyor (``BeltConveyor``): inlet ``feed`` (flows into it merge), outlet
    ``out`` (several flows out of it split by their fractions)."""

    Parameters = BeltParameters
    component = BeltConveyor

    def location(self, parameters, inlet):
        return list(parameters.start_m)

    def build(self, name, p, context):
        belt = BeltConveyor(name, context.plant, start=p.start_m, end=p.end_m,
                            speed=p.speed_m_s, bin_length=p.bin_length_m, length=p.length_m)
        context.add(belt)
        return [belt]
