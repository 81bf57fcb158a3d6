"""The test scenario for swapping crusher FMUs: only the FMU path changes."""

from __future__ import annotations

import numpy as np

from cosim import sizes
from cosim.comminution import apply_fragmentation
from cosim.fmu import CRUSHER_INTERFACE, FmuComponent
from cosim.master import Component, Master


class CrusherZone(Component):
    """Particles queue in the crusher zone; each step the oldest batch passes the jaw.

    Outputs the hardness-weighted class mass of the zone (input of the crusher
    FMU) and applies the FMU's fragmentation map to the particles that pass.
    """

    name = "zone"
    input_names = ("fragmentation_map",)

    def __init__(self, count=300, batch=10, seed=7):
        super().__init__()
        rng = np.random.default_rng(seed)
        self.f = sizes.blasted_fractions(rng, count)
        self.mass = rng.uniform(50.0, 150.0, count)
        self.hardness = rng.choice([1.0, 2.0], count)
        self.batch = batch
        self.passed = 0

    def zone(self):
        return slice(self.passed, min(self.passed + 3 * self.batch, len(self.mass)))

    def step(self, t, dt):
        fmap = self.inputs.get("fragmentation_map")
        if fmap is not None and self.passed < len(self.mass):
            passing = slice(self.passed, self.passed + self.batch)
            self.f[passing] = apply_fragmentation(self.f[passing], fmap)
            self.passed += self.batch

    def outputs(self):
        z = self.zone()
        return {"zone_hardness_mass": (self.mass[z, None] * self.hardness[z, None]
                                       * self.f[z]).sum(axis=0)}


def run_crusher_scenario(path, until=10.0):
    """The scenario: zone -> crusher FMU -> zone; only ``path`` changes between runs."""
    master = Master(step=0.5, progress=False)
    zone = master.add(CrusherZone())
    crusher = master.add(FmuComponent(path, interface=CRUSHER_INTERFACE, name="crusher_fmu",
                                      parameters={"gap_width": 0.25}))
    crusher.set_input("speed", 10.0)
    master.connect(zone, "zone_hardness_mass", crusher, "zone_hardness_mass")
    master.connect(crusher, "fragmentation_map", zone, "fragmentation_map")
    try:
        master.run(until)
    finally:
        master.finish()
    return master.timeseries, zone
