"""Jaw crusher asset: hopper, crusher zone and jaw (queue-and-zone model).

Source: paper section "Simulator": "The crusher is modeled as a jaw
crusher, drawing material from above and crushing it with a jaw driven in
an oscillatory motion. The pseudo-particles retain their original diameter,
but when they pass the jaw, the internal particle size distribution is
transformed"; the crusher torque (paper eq. crusher_torque)
tau_cr = sum over the crusher zone V_cr of m_n h_n k_cr . f_n, computed by
the crusher FMU from ``zone_hardness_mass``.

Model (the simplest that captures the asset):

* hopper: trucks dump into it; a first-in-first-out queue (no capacity
  limit; trucks never wait).
* crusher zone V_cr: holds at most ``zone_capacity`` [kg]; refilled from
  the head of the hopper every step (whole particles; one particle even if
  it alone exceeds the capacity, so the crusher never jams).
* jaw: passes the oldest zone particles at ``jaw_throughput`` [kg/s] (a
  mass credit carried between steps, as a feeder; reset while the zone is
  empty) while the downstream conveyor runs (input ``discharge_enabled``,
  default 1). A particle passing the jaw gets f := f . M with the crusher
  FMU's fragmentation map M (input ``fragmentation_map``, 16 x 16), via
  ``cosim.comminution.apply_fragmentation``, then goes to the conveyor.

Per step: jaw first, then refill, so every particle spends at least one
communication step in the zone. Output ``zone_hardness_mass`` [kg] is
sum_n m_n h_n f_n^k over the zone (16 classes): the crusher FMU's input.
The zone capacity sets the torque level; the default 900 kg gives the
paper's 1.5 kW mean power at h = 1 with the default jaw throughput
1,000 kg/s and the 15 t loads every 27.5 s (calibration, see
examples/README.md).

Events: "enter" (hopper, asset ``<name>``), "enter"/"exit" (asset
``<name>_zone``), "pass" (asset ``<name>_jaw``, state after fragmentation).
Virtual sensors (hardness, grade, size) over the zone.
"""

from __future__ import annotations

import numpy as np

from cosim.assets import Asset, AssetSensors, Plant
from cosim.comminution import apply_fragmentation
from cosim.kinds import AssetKind
from cosim.params import FmuAssetParameters, Position, Text, number
from cosim.master import CosimulationError
from cosim.numerics import weighted_column_sums

EMPTY_IDS = np.empty(0, dtype=np.uint64)


class JawCrusher(Asset):
    """Hopper + crusher zone + jaw.

    Parameters
    ----------
    name : str
        Asset name (default "crusher").
    plant : Plant
        The shared plant.
    location : (3,) array_like
        Position of the hopper (the trucks' dump point) [m].
    zone_capacity : float
        Largest mass in the crusher zone [kg] (default 900).
    jaw_throughput : float
        Mass passing the jaw per second while the zone holds material
        [kg/s] (default 1000).
    sensor_window : float
        Moving-average window of the zone's virtual sensors [s] (30).
    sensor_interval : float
        Least time between virtual-sensor samples [s] (default 0: every step).
    """

    input_names = ("fragmentation_map", "discharge_enabled")
    outlets = ("product",)
    limits_step = True
    output_names = ("zone_hardness_mass", "zone_mass_kg", "hopper_mass_kg", "passed_kg",
                    *(f"zone_{key}" for key in AssetSensors.names))

    def __init__(self, name: str, plant: Plant, *, location,
                 zone_capacity: float = 900.0, jaw_throughput: float = 1000.0,
                 sensor_window: float = 30.0, sensor_interval: float = 0.0):
        super().__init__(name, plant, location=location)
        self.zone_owner = plant.register(f"{name}_zone")
        self.zone_name = f"{name}_zone"
        self.jaw_name = f"{name}_jaw"
        self.zone_location = tuple(np.asarray(location, float) - (0.0, 0.0, 3.0))
        self.zone_capacity = float(zone_capacity)
        self.jaw_throughput = float(jaw_throughput)
        self._hopper = EMPTY_IDS
        self._zone = EMPTY_IDS
        self._credit = 0.0
        self._passed_kg = 0.0
        self._zone_hardness_mass = np.zeros(16)
        self._zone_mass = 0.0
        self._sensors = AssetSensors(self.zone_owner, sensor_window, sensor_interval)
        self._readings = self._sensors.readings

    def _accept(self, ids: np.ndarray, t: float, inlet: str) -> None:
        self._hopper = np.concatenate((self._hopper, ids))

    def step(self, t: float, dt: float) -> None:
        t_end = t + dt
        store = self.particles
        if self._zone.size and float(self.inputs.get("discharge_enabled", 1.0)) > 0.5:
            self._pass_jaw(t_end, dt)
        else:
            self._credit = 0.0
        self._refill(t_end)
        slots = store.slots(self._zone)
        if slots.size:
            mass = store.mass[slots]
            self._zone_mass = float(mass.sum())
            self._zone_hardness_mass = weighted_column_sums(mass * store.hardness[slots],
                                                            store.f[slots])
        else:
            self._zone_mass = 0.0
            self._zone_hardness_mass = np.zeros(16)
        self._readings = self._sensors.sample(store, t_end, slots)

    def _pass_jaw(self, t: float, dt: float) -> None:
        store = self.particles
        self._credit += self.jaw_throughput * dt
        slots = store.slots(self._zone)
        count = int(np.searchsorted(np.cumsum(store.mass[slots]), self._credit, side="right"))
        if count == 0:
            return
        fragmentation = self.inputs.get("fragmentation_map")
        if fragmentation is None:
            raise CosimulationError(f"{self.name}: no fragmentation_map input; connect the "
                                    "crusher FMU's fragmentation_map output")
        passing, self._zone = self._zone[:count], self._zone[count:]
        slots = slots[:count]
        self._credit -= float(store.mass[slots].sum())
        self._passed_kg += float(store.mass[slots].sum())
        self.plant.record("exit", self.zone_name, t, slots, self.zone_location)
        store.f[slots] = apply_fragmentation(store.f[slots], np.asarray(fragmentation))
        self.plant.record("pass", self.jaw_name, t, slots, self.zone_location)
        self.send("product", passing, t)

    def _refill(self, t: float) -> None:
        if self._hopper.size == 0:
            return
        store = self.particles
        room = self.zone_capacity - (float(store.mass[store.slots(self._zone)].sum())
                                     if self._zone.size else 0.0)
        hopper_slots = store.slots(self._hopper)
        count = int(np.searchsorted(np.cumsum(store.mass[hopper_slots]), room, side="right"))
        if count == 0 and self._zone.size == 0:
            count = 1
        if count == 0:
            return
        entering, self._hopper = self._hopper[:count], self._hopper[count:]
        slots = hopper_slots[:count]
        store.set_owner(slots, self.zone_owner, t)
        store.position[slots] = self.zone_location
        self.plant.record("enter", self.zone_name, t, slots, self.zone_location)
        self._zone = np.concatenate((self._zone, entering))

    def step_limit(self) -> float:
        """While the hopper or the zone holds material: the zone's capacity over the
        jaw's throughput [s] (a longer step passes at most one zone's mass, so it caps
        the throughput; ``Master`` with an adaptive step); else no limit."""
        if self._zone.size or self._hopper.size:
            return self.zone_capacity / self.jaw_throughput
        return np.inf

    def outputs(self) -> dict[str, object]:
        store = self.particles
        hopper_mass = (float(store.mass[store.slots(self._hopper)].sum())
                       if self._hopper.size else 0.0)
        return {
            "zone_hardness_mass": self._zone_hardness_mass,
            "zone_mass_kg": self._zone_mass,
            "hopper_mass_kg": hopper_mass,
            "passed_kg": self._passed_kg,
            **{f"zone_{key}": value for key, value in self._readings.items()},
        }


# ------------------------------------------------------------------ scenario kind
class CrusherParameters(FmuAssetParameters):
    """``[assets.NAME] kind = "crusher"``: a ``JawCrusher`` queue-and-zone asset with its
    crusher FMU (the jaw crusher ``"crusher"``, the cone crusher ``"cone_crusher"``, or any
    FMU in the ``crusher`` role: ``cosim.fmu.CRUSHER_INTERFACE``)."""

    position_m: Position
    """Hopper (the trucks' dump point) [m]."""
    fmu: Text = "crusher"
    """A built FMU name (fmus/build) or an .fmu path."""
    speed_rad_s: number(0.0, 1000.0, unit="rad/s") = 10.0
    zone_capacity_kg: number(0.0, 1e6, low_open=True, unit="kg") = 900.0
    jaw_throughput_kg_s: number(0.0, 1e5, low_open=True, unit="kg/s") = 1000.0


class CrusherKind(AssetKind):
    """A crusher (``JawCrusher``) and its FMU ``<name>_fmu``: inlet ``feed``, outlet
    ``product``; the FMU's torque model and fragmentation map (fmus/README.md)."""

    Parameters = CrusherParameters
    component = JawCrusher
    fmu_role = "crusher"

    def build(self, name, p, context):
        from cosim.fmu import FmuComponent, resolve_fmu
        from cosim.fmu_registry import role_interface

        sim = context.simulation
        crusher = JawCrusher(name, context.plant, location=p.position_m,
                             zone_capacity=p.zone_capacity_kg,
                             jaw_throughput=p.jaw_throughput_kg_s,
                             sensor_window=sim["sensor_window_s"],
                             sensor_interval=sim["record_every_s"])
        physics = FmuComponent(resolve_fmu(p.fmu), interface=role_interface(self.fmu_role),
                               name=f"{name}_fmu", parameters=p.parameters)
        physics.set_input("speed", p.speed_rad_s)
        context.add(crusher)
        context.add(physics)
        context.connect(crusher, "zone_hardness_mass", physics, "zone_hardness_mass")
        context.connect(physics, "fragmentation_map", crusher, "fragmentation_map")
        return [crusher]
