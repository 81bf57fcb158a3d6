"""A surge bin: every parcel stays ``residence_s`` seconds, then leaves in arrival order.

Source: plug flow with a fixed residence time, the simplest transport delay of
a bin or chute (the paper's section "Digital twin as a distributed particle
simulation": storage models range from first-in-first-out to physics-based);
written against MineTwin's public API only (``cosim.assets.Asset``,
``cosim.kinds.AssetKind``, ``cosim.params``), as a third-party package would be.

Parameters: ``position_m`` [m] (where it is), ``residence_s`` [s] (default 10 s).
Inlet ``feed``, outlet ``out``; output ``mass_kg`` [kg] (held).
"""

import numpy as np

from cosim.assets import Asset
from cosim.kinds import AssetKind
from cosim.params import Parameters, Position, number


class SurgeBin(Asset):
    output_names = ("mass_kg",)

    def __init__(self, name, plant, *, location, residence_s=10.0):
        super().__init__(name, plant, location=location)
        self.residence_s = float(residence_s)
        self._ids = np.empty(0, dtype=np.uint64)
        self._leave_at = np.empty(0)

    def _accept(self, ids, t, inlet):
        self._ids = np.concatenate((self._ids, ids))
        self._leave_at = np.concatenate((self._leave_at, np.full(ids.size, t + self.residence_s)))

    def step(self, t, dt):
        count = int(np.searchsorted(self._leave_at, t + dt, side="right"))
        if count:
            leaving, self._ids = self._ids[:count], self._ids[count:]
            self._leave_at = self._leave_at[count:]
            slots = self.particles.slots(leaving)
            self.plant.record("exit", self.name, t + dt, slots, self.location)
            self.send("out", leaving, t + dt)

    def outputs(self):
        held = self.particles.mass[self.particles.slots(self._ids)].sum() if self._ids.size else 0.0
        return {"mass_kg": float(held)}


class SurgeBinParameters(Parameters):
    position_m: Position
    residence_s: number(0.0, 3600.0, unit="s") = 10.0


class SurgeBinKind(AssetKind):
    Parameters = SurgeBinParameters
    component = SurgeBin

    def build(self, name, p, context):
        surge = SurgeBin(name, context.plant, location=p.position_m, residence_s=p.residence_s)
        context.add(surge)
        return [surge]
