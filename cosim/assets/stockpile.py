"""Stockpile asset: a storage model behind an inlet and a controlled outlet.

Source: paper section "Simulator": "The stockpile holds up to 2,000 tons
(roughly 20,000 pseudo-particles) ... When material is discharged from the
bottom outlet, at a controlled speed ranging up to 2 m/s (or 2 ton/s)";
section "Results", "Step response": the pile is filled, then discharge
starts at 500 s. Section "Digital twin as a distributed particle
simulation": micro-tracking inside storage needs a model ranging from
first-in-first-out or perfect mixing to a physics-based flow model.

Model. Which particles leave, and when, is decided by a storage model from
``cosim.storage.registered_models()`` chosen by name ("fifo", "mixing", and any
model other issues register: "rom", "dem"); this asset only does the
bookkeeping around it: inlet ("enter" events, ``receive``), the discharge
rate (a piecewise-constant schedule [(t_i, rate_i)] in kg/s, overridden by
the input ``discharge_rate`` when connected), the outlet ("exit" events,
hand-over downstream) and the capacity: output ``inlet_open`` is 0 while
the held mass is at or above ``capacity`` [kg], which the scenario wires
to stop the feeding conveyor. The held mass is kept as received minus
discharged (particles do not change mass in storage), not re-summed every
step.
"""

from __future__ import annotations

import numpy as np

from cosim.assets import Asset, AssetSensors, Plant
from cosim.errors import ValidationError
from cosim.storage import MAX_DISCHARGE_RATE, StorageModel, check_discharge_rate


class Stockpile(Asset):
    """Intermediate storage with a pluggable storage model.

    Parameters
    ----------
    name : str
        Asset name.
    plant : Plant
        The shared plant.
    model : StorageModel
        The storage model (``cosim.storage.make_storage(name)``); bound here.
    location : (3,) array_like
        Inlet (top of the pile) [m]; ``outlet`` is the feeder [m].
    capacity : float
        Largest held mass [kg] (paper: 2,000 t).
    discharge : list of (time [s], rate [kg/s])
        Piecewise-constant feeder schedule; before the first time the rate
        is 0. Rates in [0, 2000] kg/s (paper: up to 2 t/s).
    downstream : Asset
        Receives the discharged particles (the mill conveyor).
    sensor_window, sensor_interval : float
        Moving-average window of the pile's virtual sensors [s] (30) and
        least time between their samples [s] (0: every step).
    """

    input_names = ("discharge_rate",)

    def __init__(self, name: str, plant: Plant, *, model: StorageModel, location, outlet,
                 downstream, capacity: float = 2.0e6, discharge=((0.0, 0.0),),
                 sensor_window: float = 30.0, sensor_interval: float = 0.0):
        super().__init__(name, plant, location=location)
        self.outlet = tuple(float(c) for c in outlet)
        self.model = model.bind(plant.particles, self.owner)
        self.capacity = float(capacity)
        schedule = sorted((float(t), check_discharge_rate(r, MAX_DISCHARGE_RATE))
                          for t, r in discharge)
        if not schedule:
            raise ValidationError(f"{name}.discharge", "a non-empty list of [time_s, rate_kg_s]")
        self._times = np.array([t for t, _ in schedule])
        self._rates = np.array([r for _, r in schedule])
        self.downstream = downstream
        self._held_kg = 0.0
        self._discharged_kg = 0.0
        self._rate = 0.0
        self._sensors = AssetSensors(self.owner, sensor_window, sensor_interval)
        self._readings = self._sensors.readings

    def scheduled_rate(self, t: float) -> float:
        """Feeder rate of the schedule at time ``t`` [kg/s]."""
        k = int(np.searchsorted(self._times, t, side="right")) - 1
        return float(self._rates[k]) if k >= 0 else 0.0

    def _accept(self, ids: np.ndarray, t: float) -> None:
        self._held_kg += float(self.particles.mass[self.particles.slots(ids)].sum())
        self.model.receive(ids, t)

    def step(self, t: float, dt: float) -> None:
        rate = self.inputs.get("discharge_rate")
        self._rate = self.scheduled_rate(t) if rate is None else check_discharge_rate(rate)
        leaving = self.model.step(t, dt, self._rate)
        store = self.particles
        if leaving.size:
            slots = store.slots(leaving)
            store.position[slots] = self.outlet
            leaving_kg = float(store.mass[slots].sum())
            self._discharged_kg += leaving_kg
            self._held_kg -= leaving_kg
            self.plant.record("exit", self.name, t + dt, slots, self.outlet)
            self.downstream.receive(leaving, t + dt)
        self._readings = self._sensors.sample(store, t + dt)

    def outputs(self) -> dict[str, float]:
        return {"mass_kg": self._held_kg, "discharge_rate_kg_s": self._rate,
                "discharged_kg": self._discharged_kg,
                "inlet_open": 1.0 if self._held_kg < self.capacity else 0.0,
                **self._readings}
