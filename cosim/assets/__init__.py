"""Virtual assets of the 2D mine simulator, each a co-simulation ``Component``.

Source: paper section "Digital twin as a distributed particle simulation"
(every asset a is an operator u_a(t, dt) on the particles it holds; macro-
tracking events at asset boundaries; virtual sensors, eq. "observation") and
section "Simulator" (two sources, haul trucks, jaw crusher, belt conveyors,
stockpile, mill).

All assets of a scenario share one ``Plant``: one ``ParticleStore`` (an
asset's particles are those whose ``owner`` is the asset's index), one
``EventStore`` and one seeded generator. Moving particles between assets is
``Asset.receive``: the owner index changes and an event is recorded; no
particle data is copied. An asset hands the particles leaving one of its
``outlets`` to ``send(outlet, ids, t)`` inside its own ``step``; where they
go is the flow the master wired (``Master.connect_flow``). The master steps
the assets in the scenario's order (upstream first), so material handed on
is processed downstream in the same communication step.

A scenario lists assets by kind; each kind (``AssetKind``, registered
through the ``minetwin.assets`` entry points, see ``cosim.kinds``) says
which parameters it takes and builds its components.
"""

from __future__ import annotations

from collections import deque

import numba
import numpy as np

from cosim.errors import ValidationError
from cosim.events import PARTICLE_FIELDS
from cosim.master import Component
from cosim.particles import CORE_FIELDS
from cosim.sizes import N_CLASSES, mean_diameter
from cosim.stockpile_view import SOURCE_ATTRIBUTE


EVENT_FIELDS = ("id",) + PARTICLE_FIELDS
"""Particle fields captured with each event (those the event store keeps)."""
EVENT_BUFFER_ROWS = 20_000
"""Particle rows buffered by the plant before they go to the event store."""


class Plant:
    """What every asset of one scenario shares.

    Parameters
    ----------
    particles : cosim.particles.ParticleStore
        The one particle store of the scenario.
    events : cosim.events.EventStore or None
        Where macro-tracking events go (None: not recorded).
    rng : numpy.random.Generator
        The scenario's seeded generator.

    The store gets the extrinsic particle attribute ``source``: the owner
    index of the ``Source`` asset that created the particle (the ``origin``
    views show, ``cosim.stockpile_view``).

    Attributes ``mass_in`` [kg] (all mass that appeared) and ``mass_out``
    [kg] (all mass that left as product) are the plant-wide balance terms;
    ``removed_ids`` lists the particles that left the plant entirely.
    """

    def __init__(self, particles, events=None, rng: np.random.Generator | None = None):
        self.particles = particles
        if SOURCE_ATTRIBUTE not in particles.attribute_names:  # origin of what is shown
            particles.add_attribute(SOURCE_ATTRIBUTE, np.int64, -1)
        self.events = events
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.owner_names: list[str] = []
        self.mass_in = 0.0
        self.mass_out = 0.0
        self.particles_created = 0
        self._removed: list[np.ndarray] = []
        self._event_meta: list[tuple] = []
        self._event_rows = _EventRows(EVENT_BUFFER_ROWS)

    def register(self, name: str) -> int:
        """A new owner index for the particle holder called ``name``."""
        if name in self.owner_names:
            raise ValidationError("name", "unique among the plant's assets", f"{name!r} exists")
        self.owner_names.append(name)
        return len(self.owner_names) - 1

    def record(self, type: str, asset: str, t: float, slots, location) -> None:
        """Record a macro-tracking event about ``slots`` (skipped when empty).

        The particles' state is captured now, into the plant's preallocated event
        rows (one compiled gather); events are written to the event store in
        batches (``flush_events``).
        """
        if self.events is None or not len(slots):
            return
        slots = np.asarray(slots, dtype=np.int64)
        start = self._reserve_event_rows(type, asset, t, location, slots.size)
        self._event_rows.gather(self.particles, slots, start)

    def record_batch(self, type: str, asset: str, t: float, batch: dict, location) -> None:
        """Record an event about a gathered particle batch (``EVENT_FIELDS``; skipped when
        empty)."""
        if self.events is None or not len(batch["id"]):
            return
        start = self._reserve_event_rows(type, asset, t, location, len(batch["id"]))
        self._event_rows.put(batch, start)

    def _reserve_event_rows(self, type: str, asset: str, t: float, location,
                            count: int) -> int:
        """Buffer the event's own columns; the first of its ``count`` particle rows."""
        rows = self._event_rows
        if rows.used + count > rows.capacity:
            self.flush_events()
            rows.reserve(count)
        self._event_meta.append((type, asset, float(t), tuple(location), count))
        start = rows.used
        rows.used += count
        return start

    def flush_events(self) -> None:
        """Hand the buffered events to the event store in one call."""
        if self.events is None or not self._event_meta:
            return
        types, assets, times, locations, counts = zip(*self._event_meta)
        self.events.record_many(types, assets, times, locations, counts,
                                self._event_rows.filled())
        self._event_meta.clear()
        self._event_rows.used = 0

    def note_removed(self, ids: np.ndarray) -> None:
        """Remember ids of particles that left the plant (for id accounting)."""
        if ids.size:
            self._removed.append(np.asarray(ids, dtype=np.uint64).copy())

    @property
    def removed_ids(self) -> np.ndarray:
        return (np.concatenate(self._removed) if self._removed
                else np.empty(0, dtype=np.uint64))


class _EventRows:
    """Particle rows of the buffered events: one preallocated column per ``EVENT_FIELDS``
    (``used`` rows filled), so recording an event copies its particles once, in one
    compiled pass, with no per-event arrays to concatenate at the flush."""

    def __init__(self, capacity: int):
        self.capacity = 0
        self.used = 0
        self.columns: dict[str, np.ndarray] = {}
        self.reserve(capacity)

    def reserve(self, capacity: int) -> None:
        """At least ``capacity`` rows (the filled ones kept)."""
        if capacity <= self.capacity:
            return
        grown = {}
        for name in EVENT_FIELDS:
            dtype, shape = CORE_FIELDS[name]
            grown[name] = np.empty((capacity, *shape), dtype=dtype)
            if self.used:
                grown[name][:self.used] = self.columns[name][:self.used]
        self.columns, self.capacity = grown, capacity

    def gather(self, particles, slots: np.ndarray, start: int) -> None:
        """Rows ``start:start + len(slots)`` := the particles in ``slots``."""
        c = self.columns
        _gather_event_rows(slots, start, particles.id, particles.mass, particles.position,
                           particles.grade, particles.hardness, particles.origin_block,
                           particles.f, c["id"], c["mass"], c["position"], c["grade"],
                           c["hardness"], c["origin_block"], c["f"])

    def put(self, batch: dict, start: int) -> None:
        """Rows from ``start`` := a gathered batch."""
        stop = start + len(batch["id"])
        for name, column in self.columns.items():
            column[start:stop] = batch[name]

    def filled(self) -> dict[str, np.ndarray]:
        """The filled rows as a batch (views)."""
        return {name: column[:self.used] for name, column in self.columns.items()}


@numba.njit(cache=True)
def _gather_event_rows(slots, start, ids, mass, position, grade, hardness, origin_block, f,
                       out_ids, out_mass, out_position, out_grade, out_hardness,
                       out_origin_block, out_f):
    """Copy the ``EVENT_FIELDS`` of the particles in ``slots`` to rows ``start``, ... ."""
    for i in range(slots.size):
        slot, row = slots[i], start + i
        out_ids[row] = ids[slot]
        out_mass[row] = mass[slot]
        out_grade[row] = grade[slot]
        out_hardness[row] = hardness[slot]
        out_origin_block[row] = origin_block[slot]
        for k in range(position.shape[1]):
            out_position[row, k] = position[slot, k]
        for k in range(f.shape[1]):
            out_f[row, k] = f[slot, k]


class Asset(Component):
    """A virtual asset: a ``Component`` that holds particles of the shared store.

    Parameters
    ----------
    name : str
        Asset name (component name, event asset name and owner name).
    plant : Plant
        The shared plant.
    location : (3,) array_like
        Where the asset's events are located [m] (its inlet).
    """

    inlets = ("feed",)
    outlets = ("out",)

    def __init__(self, name: str, plant: Plant, location=(0.0, 0.0, 0.0)):
        super().__init__()
        self.name = name
        self.plant = plant
        self.owner = plant.register(name)
        self.location = tuple(float(c) for c in location)
        self.inlet_locations = {inlet: self.location for inlet in self.inlets}
        """Where particles entering through each inlet are [m] (default: the location)."""

    @property
    def particles(self):
        return self.plant.particles

    def particle_masses(self, ids: np.ndarray) -> np.ndarray:
        """Masses [kg] of the particles ``ids``."""
        return self.particles.mass[self.particles.slots(ids)]

    def held_mass(self) -> float:
        return float(self.particles.mass[self.particles.owner == self.owner].sum())

    def receive(self, ids: np.ndarray, t: float, inlet: str | None = None) -> None:
        """Take over particles ``ids`` at time ``t`` through ``inlet`` (default: the first):
        new owner and an "enter" event."""
        if ids.size == 0:
            return
        inlet = self.inlets[0] if inlet is None else inlet
        self._enter(ids, t, inlet)
        self._accept(ids, t, inlet)

    def _enter(self, ids: np.ndarray, t: float, inlet: str) -> None:
        """The new owner, the inlet's location and the "enter" event of ``ids``."""
        location = self.inlet_locations[inlet]
        slots = self.particles.slots(ids)
        self.particles.set_owner(slots, self.owner, t)
        self.particles.position[slots] = location
        self.plant.record("enter", self.name, t, slots, location)

    def _accept(self, ids: np.ndarray, t: float, inlet: str) -> None:
        """Hook: queue the received particles (subclasses)."""


class AssetSensors:
    """Virtual sensors of hardness, grade and size over one owner's particles.

    Paper eq. (observation): the mass-weighted mean of an attribute over the
    particles in a volume (here: the particles an asset holds),
    sum m_n p_n / sum m_n, with a moving average of window t_w [s] (default
    30 s, the paper's figures); empty samples are left out of the average.
    It is ``cosim.sensors.observe`` for all attributes at once, in one
    compiled pass over the owner array (no gathers), because it runs every
    step for three assets, one of them holding ~20,000 particles. Outputs
    per sample: ``hardness``, ``hardness_avg``, ``grade``, ``grade_avg`` [-] and
    ``d_mean``, ``d_mean_avg`` [m], the mean particle diameter d . f of the
    (averaged) size distribution (paper, same section); NaN while empty.
    ``interval`` [s] (default 0: every call) limits the sampling rate; the
    scenario samples at its recording interval.
    """

    names = ("hardness", "hardness_avg", "grade", "grade_avg", "d_mean", "d_mean_avg")
    """The readings, in order."""

    def __init__(self, owner: int, window: float = 30.0, interval: float = 0.0):
        self.owner = owner
        self.window = float(window)
        self.interval = float(interval)
        self._next = 0.0
        self._samples: deque = deque()
        self._sum = np.zeros(N_CLASSES + 2)
        self.readings = self._empty()

    @staticmethod
    def _empty() -> dict[str, float]:
        return {key: float("nan") for key in AssetSensors.names}

    def sample(self, particles, t: float, slots=None) -> dict[str, float]:
        """Observe at time ``t`` (at most once per ``interval``); the readings.

        ``slots``: the asset's particles when it knows them (cheaper than a
        pass over the owner array).
        """
        if t < self._next - 1e-9:
            return self.readings
        self._next = t + self.interval
        if slots is None:
            total, value = _owner_sums(particles.owner, self.owner, particles.mass,
                                       particles.hardness, particles.grade, particles.f)
        else:
            total, value = _slot_sums(np.asarray(slots, dtype=np.int64), particles.mass,
                                      particles.hardness, particles.grade, particles.f)
        readings = self._empty()
        if total > 0:
            value /= total          # [hardness, grade, f_0..f_15], mass-weighted
            self._samples.append((t, value))
            self._sum += value
            readings.update(hardness=float(value[0]), grade=float(value[1]),
                            d_mean=float(mean_diameter(value[2:])))
        while self._samples and self._samples[0][0] <= t - self.window:
            self._sum -= self._samples.popleft()[1]
        if self._samples:
            average = self._sum / len(self._samples)
            readings.update(hardness_avg=float(average[0]), grade_avg=float(average[1]),
                            d_mean_avg=float(mean_diameter(average[2:])))
        else:
            self._sum[:] = 0.0
        self.readings = readings
        return readings


@numba.njit(cache=True)
def _owner_sums(owner, target, mass, hardness, grade, f):
    """sum m and sum m [h, c, f_0..f_15] over the particles of one owner (one pass).

    Twin of ``_slot_sums`` on purpose: fusing the owner test into the sum
    saves building a slot array every step (measured 5-10 % of the paper-scale
    run's speed, benchmarks/bench_mine.py)."""
    n, classes = f.shape
    total = 0.0
    sums = np.zeros(classes + 2)
    for i in range(n):
        if owner[i] == target:
            m = mass[i]
            total += m
            sums[0] += m * hardness[i]
            sums[1] += m * grade[i]
            for k in range(classes):
                sums[2 + k] += m * f[i, k]
    return total, sums


@numba.njit(cache=True)
def _slot_sums(slots, mass, hardness, grade, f):
    """sum m and sum m [h, c, f_0..f_15] over the particles in ``slots``."""
    classes = f.shape[1]
    total = 0.0
    sums = np.zeros(classes + 2)
    for i in slots:
        m = mass[i]
        total += m
        sums[0] += m * hardness[i]
        sums[1] += m * grade[i]
        for k in range(classes):
            sums[2 + k] += m * f[i, k]
    return total, sums


class PlantBalance(Component):
    """Plant-wide mass balance and particle count, recorded every step.

    mass in (everything that appeared at the sources) = mass held by all
    assets (the particle store's total) + mass out (product). Outputs
    ``mass_in_kg``, ``mass_held_kg``, ``mass_out_kg``,
    ``mass_balance_rel_error`` = |in - held - out| / in (0 before any mass
    appeared) and ``particles`` (count held). Add it last, so it sees every
    asset's step.
    """

    output_names = ("mass_in_kg", "mass_held_kg", "mass_out_kg", "mass_balance_rel_error",
                    "particles")

    def __init__(self, plant: Plant, name: str = "plant"):
        super().__init__()
        self.name = name
        self.plant = plant

    def outputs(self) -> dict[str, float]:
        held = float(self.plant.particles.mass.sum())
        mass_in, mass_out = self.plant.mass_in, self.plant.mass_out
        error = abs(mass_in - held - mass_out) / mass_in if mass_in > 0 else 0.0
        return {"mass_in_kg": mass_in, "mass_held_kg": held, "mass_out_kg": mass_out,
                "mass_balance_rel_error": error,
                "particles": float(len(self.plant.particles))}

    def step(self, t: float, dt: float) -> None:
        """Nothing to advance: the balance is read from the plant."""
