"""Mill asset: holds the charge's particles and applies the mill FMU's operators.

Source: paper section "Simulator" (idealised mill after Araker 2020): "When
a pseudo-particle n reach the grinder, a size reduction model begins to
operate on its size distribution. Each size fraction k is assigned a
probability per unit time P_n^k for breaking into smaller fractions and a
probability per unit time Q_n^k for leaving the mill." The physics (rates,
torques, power) is the mill FMU's; this asset supplies the FMU's input
``charge_mass`` [kg] (mass per size class of the charge, sum_n m_n f_n^k)
and applies the FMU's outputs ``breakage_rate`` (1/s for hardness 1; a
particle of hardness h breaks at P^k / h), ``daughter_fraction`` (16 x 16)
and ``escape_rate`` (1/s) to every particle it holds with
``cosim.comminution.mill_step`` (exact exponential update over a step).

Mass that escapes through the classifier leaves the plant as product. It is
reported in "product" events every ``product_event_interval`` [s]: one
event listing each particle that lost mass, with the mass it lost in the
interval as the event's particle mass. A particle whose remaining mass falls
below ``product_threshold`` [kg] leaves entirely (its remainder counts as
product) and is removed from the particle store.
"""

from __future__ import annotations

import numpy as np

from cosim.assets import EVENT_FIELDS, Asset, AssetSensors, Plant
from cosim.comminution import METHODS, mill_operators, mill_step_held
from cosim.errors import ValidationError
from cosim.kinds import AssetKind
from cosim.params import FmuAssetParameters, Position, Text, choice, number
from cosim.master import CosimulationError
from cosim.numerics import weighted_column_sums

OPERATOR_INPUTS = ("breakage_rate", "daughter_fraction", "escape_rate")


class Mill(Asset):
    """Grinding mill holding particles; physics from the mill FMU.

    Parameters
    ----------
    name : str
        Asset name.
    plant : Plant
        The shared plant.
    location : (3,) array_like
        Mill inlet [m].
    product_threshold : float
        A particle lighter than this [kg] has been ground out: it leaves
        the plant whole (default 0.01 kg).
    product_event_interval : float
        Interval of the "product" events [s] (default 60 s).
    method : str
        Integration method of ``cosim.comminution.mill_step``
        (default "exponential").
    update_interval : float
        Least time between applications of the operators [s] (default 0:
        every communication step). The exponential integrator is stable for
        any step, so a mill holding thousands of particles may be updated
        less often than the master communicates; the elapsed time is applied
        at once with the FMU's latest operators, and ``charge_mass`` follows.
    sensor_window : float
        Moving-average window of the charge's virtual sensors [s] (30).
    sensor_interval : float
        Least time between virtual-sensor samples [s] (default 0: every step).
    """

    input_names = OPERATOR_INPUTS
    outlets = ()    # the product leaves the plant
    output_names = ("charge_mass", "mass_kg", "product_kg", "product_rate_kg_s",
                    *AssetSensors.names)

    def __init__(self, name: str, plant: Plant, *, location, product_threshold: float = 0.01,
                 product_event_interval: float = 60.0, method: str = "exponential",
                 update_interval: float = 0.0, sensor_window: float = 30.0,
                 sensor_interval: float = 0.0):
        super().__init__(name, plant, location=location)
        if method not in METHODS:
            raise ValidationError(f"{name}.method", f"one of {list(METHODS)}",
                                  f"got {method!r}")
        self.product_threshold = float(product_threshold)
        self.product_event_interval = float(product_event_interval)
        self.method = method
        self.update_interval = float(update_interval)
        self._next_update = self.update_interval
        self._elapsed = 0.0
        self._ids = np.empty(0, dtype=np.uint64)
        self._pending = np.empty(0)          # product mass per held particle since last event
        self._next_event = self.product_event_interval
        self._charge = np.zeros(16)
        self._product_kg = 0.0
        self._product_rate = 0.0
        self._sensors = AssetSensors(self.owner, sensor_window, sensor_interval)
        self._readings = self._sensors.readings

    def _accept(self, ids: np.ndarray, t: float, inlet: str) -> None:
        self._ids = np.concatenate((self._ids, ids))
        self._pending = np.concatenate((self._pending, np.zeros(ids.size)))

    def step(self, t: float, dt: float) -> None:
        t_end = t + dt
        self._elapsed += dt
        if t_end < self._next_update - 1e-9:
            return
        dt, self._elapsed = self._elapsed, 0.0
        self._next_update = t_end + self.update_interval
        store = self.particles
        escaped_total = 0.0
        if self._ids.size:
            missing = [name for name in OPERATOR_INPUTS if self.inputs.get(name) is None]
            if missing:
                raise CosimulationError(f"{self.name}: no {missing} input; connect the mill "
                                        "FMU's outputs")
            slots = store.slots(self._ids)
            # the FMU's operators are checked (one compiled pass); the held particles'
            # mass and hardness were checked when they entered the store
            operators = mill_operators(self.inputs["breakage_rate"],
                                       self.inputs["daughter_fraction"],
                                       self.inputs["escape_rate"])
            new_f, new_mass, escaped = mill_step_held(
                store.f[slots], store.mass[slots], store.hardness[slots], operators, dt,
                method=self.method)
            store.f[slots] = new_f
            store.mass[slots] = new_mass
            self._pending += escaped
            escaped_total = float(escaped.sum())
            self.plant.mass_out += escaped_total
            ground_out = new_mass < self.product_threshold
            kept = ~ground_out
            self._charge = weighted_column_sums(new_mass[kept], new_f[kept])
            if ground_out.any() or t_end >= self._next_event - 1e-9:
                escaped_total += self._report_product(slots, ground_out, t_end)
            if ground_out.any():        # removal moved rows: look the slots up again
                slots = store.slots(self._ids)
        else:
            slots = np.empty(0, dtype=np.int64)
            self._charge = np.zeros(16)
        self._product_kg += escaped_total
        self._product_rate = escaped_total / dt
        self._readings = self._sensors.sample(store, t_end, slots)

    def _report_product(self, slots, ground_out, t: float) -> float:
        """Record "product" events and remove ground-out particles; their remainder [kg]."""
        store = self.particles
        remainder = float(store.mass[slots[ground_out]].sum())
        self.plant.mass_out += remainder
        pending = self._pending + np.where(ground_out, store.mass[slots], 0.0)
        if t >= self._next_event - 1e-9:
            report = pending > 0
            self._next_event += self.product_event_interval
        else:
            report = ground_out
        if report.any():
            batch = store.gather(slots[report], fields=EVENT_FIELDS)
            batch["mass"] = pending[report]
            self.plant.record_batch("product", self.name, t, batch, self.location)
            self._pending[report] = 0.0
        if ground_out.any():
            leaving = self._ids[ground_out]
            store.remove(leaving)
            self.plant.note_removed(leaving)
            self._ids = self._ids[~ground_out]
            self._pending = self._pending[~ground_out]
        return remainder

    def outputs(self) -> dict[str, object]:
        return {"charge_mass": self._charge, "mass_kg": float(self._charge.sum()),
                "product_kg": self._product_kg, "product_rate_kg_s": self._product_rate,
                **self._readings}


# ------------------------------------------------------------------ scenario kind
class MillParameters(FmuAssetParameters):
    """``[assets.NAME] kind = "mill"``: a ``Mill`` with its mill FMU (``"mill"`` or any FMU
    in the ``mill`` role: ``cosim.fmu.MILL_INTERFACE``)."""

    position_m: Position
    """Mill inlet [m]."""
    fmu: Text = "mill"
    speed_rad_s: number(0.0, 100.0, unit="rad/s") = 1.2
    product_threshold_kg: number(0.0, 1e3, low_open=True, unit="kg") = 0.01
    product_event_interval_s: number(0.0, 1e5, low_open=True, unit="s") = 60.0
    update_interval_s: number(0.0, 60.0, unit="s") = 0.0
    integrator: choice(*METHODS) = "exponential"
    """The population balance's integrator (``cosim.comminution``): "exponential"
    (stable for any step), "explicit" (the paper's; unstable above its limit) or
    "auto" (the explicit update only where it is safely stable)."""


class MillKind(AssetKind):
    """A mill (``Mill``) and its FMU ``<name>_fmu``: inlet ``feed``; the product leaves the
    plant (no outlet)."""

    Parameters = MillParameters
    component = Mill
    fmu_role = "mill"

    def build(self, name, p, context):
        from cosim.fmu import FmuComponent, resolve_fmu
        from cosim.fmu_registry import role_interface

        sim = context.simulation
        mill = Mill(name, context.plant, location=p.position_m,
                    product_threshold=p.product_threshold_kg,
                    product_event_interval=p.product_event_interval_s,
                    update_interval=p.update_interval_s, sensor_window=sim["sensor_window_s"],
                    sensor_interval=sim["record_every_s"], method=p.integrator)
        physics = FmuComponent(resolve_fmu(p.fmu), interface=role_interface(self.fmu_role),
                               name=f"{name}_fmu", parameters=p.parameters)
        physics.set_input("speed_setpoint", p.speed_rad_s)
        context.add(mill)
        context.add(physics)
        context.connect(mill, "charge_mass", physics, "charge_mass")
        for signal in OPERATOR_INPUTS:
            context.connect(physics, signal, mill, signal)
        return [mill]
