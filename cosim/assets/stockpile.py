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
bookkeeping around it: the inlets ("enter" events, ``receive``), the
discharge rate of each outlet (a piecewise-constant schedule [(t_i, rate_i)]
in kg/s, overridden by the input ``discharge_rate_<outlet>`` when
connected), the outlets ("exit" events, hand-over along the flows) and the
capacity: output ``inlet_open`` is 0 while
the held mass is at or above ``capacity`` [kg], which the scenario wires
to stop the feeding conveyor. The held mass is kept as received minus
discharged (particles do not change mass in storage), not re-summed every
step.
"""

from __future__ import annotations

import sys

import numba
import numpy as np
from pydantic import model_validator

from cosim.assets import Asset, AssetSensors, Plant
from cosim.errors import ValidationError
from cosim.kinds import AssetKind
from cosim.params import Parameters, Position, Schedule, Text, number, refuse, refuse_from
from cosim.storage import MAX_DISCHARGE_RATE, StorageModel, check_discharge_rate


class Stockpile(Asset):
    """Intermediate storage with a pluggable storage model, several inlets and outlets.

    Parameters
    ----------
    name : str
        Asset name.
    plant : Plant
        The shared plant.
    model : StorageModel
        The storage model (``cosim.storage.make_storage(name)``); bound here.
    inlets : dict of name -> (3,) array_like
        Entry points and where they are [m] (the paper's pile has two); the
        asset's location is the first one's.
    outlets : dict of name -> ((3,) array_like, list of (time [s], rate [kg/s]))
        Exit points (the paper's pile has four), each with its position [m]
        and its own piecewise-constant feeder schedule; before the first time
        the rate is 0. Rates in [0, 2000] kg/s (paper: up to 2 t/s). Input
        ``discharge_rate_<outlet>`` [kg/s] overrides an outlet's schedule.
    capacity : float
        Largest held mass [kg] (paper: 2,000 t).
    sensor_window, sensor_interval : float
        Moving-average window of the pile's virtual sensors [s] (30) and
        least time between their samples [s] (0: every step).

    The storage model decides which particles leave at the outlets' summed
    rate; with several outlets each takes, in the order they leave, the
    particles its own mass credit (rate x time) pays for. That is exact for
    models without geometry (FIFO, mixing: every outlet draws on one queue);
    a model that resolves where the outlets are would choose per outlet.
    Outputs ``discharge_rate_kg_s`` and ``discharged_kg`` are the totals;
    with several outlets ``discharge_rate_kg_s_<outlet>`` and
    ``discharged_kg_<outlet>`` follow each.
    """

    def __init__(self, name: str, plant: Plant, *, model: StorageModel, inlets: dict,
                 outlets: dict, capacity: float = 2.0e6, sensor_window: float = 30.0,
                 sensor_interval: float = 0.0, switcher=None):
        if not inlets or not outlets:
            raise ValidationError(f"{name}.inlets", "at least one inlet and one outlet")
        locations = {inlet: tuple(float(c) for c in where) for inlet, where in inlets.items()}
        self.inlets = tuple(inlets)
        self.outlets = tuple(outlets)
        super().__init__(name, plant, location=next(iter(locations.values())))
        self.inlet_locations = locations
        self.outlet_locations = {outlet: tuple(float(c) for c in where)
                                 for outlet, (where, _) in outlets.items()}
        self.input_names = tuple(f"discharge_rate_{outlet}" for outlet in self.outlets)
        self._rate_inputs = tuple(zip(self.outlets, self.input_names))
        self.model = model.bind(plant.particles, self.owner)
        self.fidelity = None  # the choice of a model = "auto" stockpile (cosim.fidelity)
        self.switcher = switcher
        self.capacity = float(capacity)
        self._schedules = {}
        for outlet, (_, discharge) in outlets.items():
            schedule = sorted((float(t), check_discharge_rate(r, MAX_DISCHARGE_RATE))
                              for t, r in discharge)
            if not schedule:
                raise ValidationError(f"{name}.outlets.{outlet}.discharge",
                                      "a non-empty list of [time_s, rate_kg_s]")
            self._schedules[outlet] = (np.array([t for t, _ in schedule]),
                                       np.array([r for _, r in schedule]))
        self._held_kg = 0.0
        self._rate_kg_s = 0.0
        self._discharged_kg = 0.0
        self._discharged = {outlet: 0.0 for outlet in self.outlets}
        self._rates = {outlet: 0.0 for outlet in self.outlets}
        self._credit = np.zeros(len(self.outlets))
        self._sensors = AssetSensors(self.owner, sensor_window, sensor_interval)
        self._readings = self._sensors.readings
        self._several = several = len(self.outlets) > 1
        self.output_names = ("mass_kg", "discharge_rate_kg_s", "discharged_kg", "inlet_open",
                             *AssetSensors.names,
                             *(f"{key}_{outlet}" for outlet in self.outlets if several
                               for key in ("discharge_rate_kg_s", "discharged_kg")),
                             *(("model_rung",) if switcher is not None else ()))

    def scheduled_rate(self, t: float, outlet: str | None = None) -> float:
        """Feeder rate of ``outlet``'s schedule at time ``t`` [kg/s]; without ``outlet``,
        the sum over the outlets (what the storage model is asked to discharge)."""
        if outlet is None:
            return sum(self.scheduled_rate(t, name) for name in self.outlets)
        times, rates = self._schedules[outlet]
        k = int(np.searchsorted(times, t, side="right")) - 1
        return float(rates[k]) if k >= 0 else 0.0

    def prefill(self, ids: np.ndarray, t: float) -> None:
        """The pile's earlier production at time ``t``: received through the first
        inlet ("enter" events) and laid by the storage model as the pile it held
        (``StorageModel.prefill``), not as inflow."""
        if ids.size == 0:
            return
        self._enter(ids, t, self.inlets[0])
        self._held_kg += float(self.particles.mass[self.particles.slots(ids)].sum())
        self.model.prefill(ids, t)

    def _accept(self, ids: np.ndarray, t: float, inlet: str) -> None:
        self._held_kg += float(self.particles.mass[self.particles.slots(ids)].sum())
        self.model.receive(ids, t)

    def step(self, t: float, dt: float) -> None:
        total = 0.0
        for outlet, name in self._rate_inputs:
            rate = self.inputs.get(name)
            rate = self.scheduled_rate(t, outlet) if rate is None else check_discharge_rate(rate)
            self._rates[outlet] = rate
            total += rate
        self._rate_kg_s = total
        if self.switcher is not None:
            self._switch(t, total)
        leaving = self.model.step(t, dt, total)
        store = self.particles
        if not self._several:
            if leaving.size:
                self._discharge(store, self.outlets[0], leaving, store.slots(leaving), t + dt)
        else:
            self._credit += np.array([self._rates[o] for o in self.outlets]) * dt
            if leaving.size:
                slots = store.slots(leaving)
                choice = _credit_choice(store.mass[slots], self._credit)
                for k, outlet in enumerate(self.outlets):
                    mine = choice == k
                    if mine.any():
                        self._discharge(store, outlet, leaving[mine], slots[mine], t + dt)
            if self.model.held_ids().size == 0:
                self._credit[:] = 0.0     # an empty pile owes nothing (as the feeder's credit)
        self._readings = self._sensors.sample(store, t + dt)

    def _switch(self, t: float, rate: float) -> None:
        switches = len(self.switcher.switches)
        self.model = self.switcher.update(t, self.model, rate)
        if len(self.switcher.switches) > switches:
            switch = self.switcher.switches[-1]
            print(f"{self.name}: t = {t:g} s, {switch['from_model']} -> {switch['to_model']}: "
                  f"{switch['reason']}", file=sys.stderr)
            self.plant.record("switch", self.name, t,
                              self.particles.slots(self.model.held_ids()), self.location)
            self.fidelity["switches"] = list(self.switcher.switches)

    def _discharge(self, store, outlet: str, ids, slots, t: float) -> None:
        where = self.outlet_locations[outlet]
        store.position[slots] = where
        leaving_kg = float(store.mass[slots].sum())
        self._discharged[outlet] += leaving_kg
        self._discharged_kg += leaving_kg
        self._held_kg -= leaving_kg
        self.plant.record("exit", self.name, t, slots, where)
        self.send(outlet, ids, t)

    def outputs(self) -> dict[str, float]:
        out = {"mass_kg": self._held_kg, "discharge_rate_kg_s": self._rate_kg_s,
               "discharged_kg": self._discharged_kg,
               "inlet_open": 1.0 if self._held_kg < self.capacity else 0.0,
               **self._readings}
        if self._several:
            for outlet in self.outlets:
                out[f"discharge_rate_kg_s_{outlet}"] = self._rates[outlet]
                out[f"discharged_kg_{outlet}"] = self._discharged[outlet]
        if self.switcher is not None:  # which model runs: 0 the cheapest card, up the ladder
            out["model_rung"] = float(self.switcher.rungs.index(self.switcher.ladder.model))
        return out


@numba.njit(cache=True)
def _credit_choice(masses, credit):
    """Outlet per leaving particle: the one with the most credit [kg] (updated in place)."""
    choice = np.empty(masses.size, dtype=np.int64)
    for i in range(masses.size):
        best = 0
        for k in range(1, credit.size):
            if credit[k] > credit[best]:
                best = k
        choice[i] = best
        credit[best] -= masses[i]
    return choice


# ------------------------------------------------------------------ scenario kind
class InletParameters(Parameters):
    position_m: Position
    """Where the inlet is [m] (the paper's pile: on top)."""


class OutletParameters(Parameters):
    position_m: Position
    """Where the outlet's feeder is [m] (the paper's pile: at the bottom)."""
    discharge: Schedule = [[0.0, 0.0]]
    """Feeder schedule [[time_s, rate_kg_s], ...] (rates <= 2000 kg/s)."""


class InitialFill(Parameters):
    """Earlier production in the pile at t = 0 (``fill_stockpile``)."""

    mass_kg: number(0.0, 1e9, unit="kg")
    trucks: Text
    """The truck fleet whose first truck's loads (route and payload) fill the pile."""
    crusher: Text
    """The crusher whose FMU's fragmentation map crushed them."""


class Accuracy(Parameters):
    """The accuracy a ``model = "auto"`` stockpile must track its outflow with."""

    tracking_error: number(0.0, 1.0)
    """Largest tracking error (fraction of the outflow mass, ``cosim.fidelity``)."""
    window_s: number(0.0, 3600.0, low_open=True, unit="s") = 30.0
    """Window of the tracking error [s]."""


class Budget(Parameters):
    """The cost a ``model = "auto"`` stockpile may take."""

    wall_s_per_s: number(0.0, 1e6, low_open=True, unit="s/s")
    """Largest wall seconds per simulated second of the storage model."""


class Switching(Parameters):
    """How a ``model = "auto"`` stockpile moves along its ladder during a run
    (``cosim.fidelity.Ladder``)."""

    margin: number(0.0, 0.5) = 0.1
    """Fraction of each bound of a cheaper card's range the scene must be inside
    before the pile goes back down to it [-]."""
    dwell_s: number(0.0, 1e6, unit="s") = 30.0
    """How long it must stay there first [s]."""


class StockpileParameters(Parameters):
    """``[assets.NAME] kind = "stockpile"``: see ``Stockpile``; ``inlets`` and ``outlets``
    are tables of named entry and exit points (``[assets.NAME.outlets.east]``).
    ``model = "auto"`` with ``accuracy`` (or ``budget``) runs the cheapest model whose
    fidelity card meets it (``choose_storage``; ``cards``: a cards file, default the
    registered ones)."""

    model: Text = "fifo"
    """Storage model (``cosim.storage``): fifo, mixing, rom, dem, ..., or "auto"."""
    options: dict = {}
    """Keyword options of the storage model."""
    capacity_kg: number(0.0, 1e9, low_open=True, unit="kg") = 2.0e6
    inlets: dict[str, InletParameters]
    outlets: dict[str, OutletParameters]
    initial_fill: InitialFill | None = None
    accuracy: Accuracy | None = None
    budget: Budget | None = None
    cards: Text | None = None
    switching: Switching = Switching()

    @model_validator(mode="after")
    def _complete(self):
        from cosim.storage import check_storage_options, storage_class

        if not self.inlets:
            raise refuse("inlets", "at least one [inlets.NAME] table", "got none")
        if not self.outlets:
            raise refuse("outlets", "at least one [outlets.NAME] table", "got none")
        if self.model == AUTO:
            if (self.accuracy is None) == (self.budget is None):
                raise refuse("accuracy", "an accuracy or a budget table (one of them) with "
                             'model = "auto"', "got both" if self.accuracy else "got neither")
            if set(self.options) - {"model"}:
                raise refuse("options", 'only "model" (the ROM file, given to the ROM if '
                             'chosen) with model = "auto"', f"got {sorted(self.options)}")
            return self
        for key in ("accuracy", "budget", "cards"):
            if getattr(self, key) is not None:
                raise refuse(key, 'absent unless model = "auto"', f"model is {self.model!r}")
        try:
            storage_class(self.model, "model")
            check_storage_options(self.model, self.options, "options")
        except ValidationError as exc:
            raise refuse_from(exc) from None
        if self.initial_fill is not None and self.initial_fill.mass_kg > self.capacity_kg:
            raise refuse("initial_fill.mass_kg", f"finite and >= 0 and <= {self.capacity_kg:g}"
                         " kg (the capacity)", f"got {self.initial_fill.mass_kg!r}")
        return self


class StockpileKind(AssetKind):
    """A stockpile (``Stockpile``) with its storage model; named inlets and outlets."""

    Parameters = StockpileParameters
    component = Stockpile

    def ports(self, parameters):
        return tuple(parameters.inlets), tuple(parameters.outlets)

    def location(self, parameters, inlet):
        return list(parameters.inlets[inlet].position_m)

    def check(self, name, parameters, plant):
        fill = parameters.initial_fill
        if fill is None:
            return []
        declared = list(plant.assets)
        before = declared[:declared.index(name)]
        errors = []
        for key, wanted in (("trucks", "truck_fleet"), ("crusher", "crusher")):
            value = getattr(fill, key)
            if value not in before or plant.kind_names[value] != wanted:
                errors.append(ValidationError(
                    f"assets.{name}.initial_fill.{key}",
                    f"a {wanted} asset declared before {name}", f"got {value!r}"))
        return errors

    def build(self, name, p, context):
        sim = context.simulation
        choice, switcher = choose_storage(name, p, [sim["seed"], 1]) if p.model == AUTO \
            else (None, None)
        model = choice.model if choice is not None else p.model
        options = p.options if model == p.model or model == "rom" else {}
        pile = Stockpile(name, context.plant, model=_storage(model, options, [sim["seed"], 1]),
                         switcher=switcher,
                         inlets={k: v.position_m for k, v in p.inlets.items()},
                         outlets={k: (v.position_m, v.discharge) for k, v in p.outlets.items()},
                         capacity=p.capacity_kg, sensor_window=sim["sensor_window_s"],
                         sensor_interval=sim["record_every_s"])
        pile.fidelity = None if choice is None else choice.to_json()
        context.add(pile)
        fill = p.initial_fill
        if fill is not None and fill.mass_kg > 0:
            crusher_fmu = next(c for c in context.master.components
                               if c.name == f"{fill.crusher}_fmu")
            fill_stockpile(pile, context.built[fill.trucks][0],
                           crusher_fmu.outputs()["fragmentation_map"], fill.mass_kg)
        return [pile]


AUTO = "auto"
"""The stockpile's ``model`` that lets its fidelity cards choose (``choose_storage``)."""


def choose_storage(name: str, p: StockpileParameters, seed):
    """The storage model a ``model = "auto"`` stockpile runs: the cheapest whose
    fidelity card meets ``p.accuracy`` (or the most accurate within ``p.budget``)
    at the scene's operating point (``cosim.fidelity.choose``). The operating
    point is conservative: the largest scheduled discharge summed over the
    outlets, the initial fill as the held mass. A ROM card counts only with the
    ROM file it was measured on (``options.model``, else the ROM's
    ``default_model_file``, by SHA-256); the cards that ROM file carries beside it
    (``cosim.fidelity.own_cards_file``) are read too. Prints the
    choice and why on stderr. Returns the ``Choice`` and the ``Switcher`` that
    hands the pile up or down the ladder during the run (``cosim.handover``:
    hysteresis margin ``p.switching.margin``, dwell ``p.switching.dwell_s``)."""
    import hashlib
    import sys
    from pathlib import Path

    from cosim.fidelity import (Ladder, OperatingPoint, choose, own_cards_file, read_cards,
                                registered_cards)
    from cosim.handover import Switcher
    from cosim.storage import registered_models, storage_class

    cards = read_cards(p.cards) if p.cards else registered_cards()
    rom_file = p.options.get("model")
    if rom_file is None and "rom" in registered_models():
        card_file = storage_class("rom").default_model_file
    else:
        card_file = rom_file
    rom_digest = (hashlib.sha256(Path(card_file).read_bytes()).hexdigest()
                  if isinstance(card_file, (str, Path)) and Path(card_file).is_file() else None)
    own_cards = own_cards_file(card_file) if rom_digest is not None else None
    if own_cards is not None and own_cards.is_file():
        cards = cards + read_cards(own_cards)  # the ROM's own card
    usable = [c for c in cards if c.model in registered_models()
              and (c.model != "rom" or c.provenance.get("model_sha256") == rom_digest)]
    throughput = sum(max(rate for _, rate in outlet.discharge) for outlet in p.outlets.values())
    held = p.initial_fill.mass_kg if p.initial_fill is not None else 0.0
    window = p.accuracy.window_s if p.accuracy is not None else 30.0
    point = OperatingPoint(throughput_kg_s=min(throughput, MAX_DISCHARGE_RATE),
                           held_mass_kg=held, window_s=window)
    choice = choose(usable, point, field_name=f"assets.{name}",
                    tracking_error=p.accuracy.tracking_error if p.accuracy else None,
                    wall_s_per_s=p.budget.wall_s_per_s if p.budget else None)
    print(f"{name}: model auto -> {choice.model}: {choice.reason} at "
          f"{point.throughput_kg_s:g} kg/s and {held / 1e3:g} t", file=sys.stderr)
    target = ({"tracking_error": p.accuracy.tracking_error} if p.accuracy else
              {"wall_s_per_s": p.budget.wall_s_per_s})
    ladder = Ladder(usable, margin=p.switching.margin, dwell_s=p.switching.dwell_s, **target)
    ladder.model = choice.model
    rng = np.random.default_rng(seed)

    def build(model):
        options = {"model": rom_file} if model == "rom" and rom_file else {}
        return _storage(model, options, rng.integers(2 ** 63))

    return choice, Switcher(ladder, build, window_s=window,
                            rungs=[c["model"] for c in choice.compared])


def _storage(name: str, options: dict, rng_seed) -> StorageModel:
    from cosim.storage import make_storage

    return make_storage(name, rng=np.random.default_rng(rng_seed), **options)


def fill_stockpile(stockpile, truck, fragmentation_map, mass: float) -> None:
    """Put ``mass`` [kg] of earlier production into the stockpile at t = 0.

    The material is what the plant would have made before the run: truck
    loads of ``truck.payload`` [kg] taken in turn from the truck's route
    (the loading faces advance, "appear" events at t = 0) and crushed with
    the crusher FMU's fragmentation map, then received by the stockpile
    ("enter" events at t = 0, first inlet). It gives the stockpile the
    paper's scale (2,000 t, about 20,000 particles) without simulating the
    hours of filling.
    """
    from cosim.comminution import apply_fragmentation

    store = stockpile.particles
    remaining, k = float(mass), 0
    while remaining > 1e-9:
        load = min(truck.payload, remaining)
        ids = truck.route[k % len(truck.route)].take(load, 0.0)
        slots = store.slots(ids)
        store.f[slots] = apply_fragmentation(store.f[slots], fragmentation_map)
        stockpile.prefill(ids, 0.0)
        remaining -= load
        k += 1
