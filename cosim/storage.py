"""Storage models (stockpile, bin, chute) behind one interface.

Source: paper sections "Introduction" and "Digital twin as a distributed
particle simulation": micro-tracking in chutes, silos and stockpiles needs a
model "that may range from simple first-in-first-out or perfect mixing
models, to a physics-based flow model"; they form a fidelity ladder
(docs/architecture.md): plug flow (FIFO) < perfect mixing < reduced-order model
(ROM) < DEM.

Every model has the same calls (scikit-learn style):

``fit(data=None)``
    learn from data (the ROM trains here; FIFO and mixing have nothing to
    learn and return ``self``).
``bind(particles, owner)``
    attach to a ``ParticleStore`` and the owner index of the storage asset.
``receive(ids, t)``
    particles that the caller has just handed to the storage (owner set).
``step(t, dt, discharge_rate)``
    advance by ``dt`` [s] with the feeder at ``discharge_rate`` [kg/s];
    returns the ids of the particles that reached the outlet, which the
    caller hands on. Particles leave whole; the feeder keeps a mass credit
    so that the discharged mass follows rate * time to within one particle.
``predict(horizon, discharge_rate)``
    the feed predicted for the next ``horizon`` seconds: ``(ids, mass)``,
    the particles expected to leave and the mass [kg] of each expected to
    leave (paper section "Predicting the properties of the mill feed").

Models are registered by name in ``STORAGE_MODELS``; ``make_storage(name)``
builds one, importing the costly ones lazily.
"""

from __future__ import annotations

import importlib

import numpy as np

from cosim.errors import ValidationError

MAX_DISCHARGE_RATE = 2000.0
"""Largest feeder rate [kg/s] (paper: up to 2 t/s)."""


def check_discharge_rate(rate: float, limit: float = MAX_DISCHARGE_RATE) -> float:
    """Refuse a discharge rate outside [0, limit] kg/s."""
    rate = float(rate)
    if not np.isfinite(rate) or rate < 0 or rate > limit:
        raise ValidationError("discharge_rate", f"in [0, {limit:g}] kg/s", f"got {rate!r}")
    return rate


class StorageModel:
    """Base class: bookkeeping shared by every storage model.

    Subclasses implement ``_order_of_leaving(count)`` (which held particles
    the feeder takes next) or override ``step`` entirely (ROM, DEM).
    """

    name = "base"

    def __init__(self):
        self.particles = None
        self.owner = None
        self._credit_kg = 0.0

    def fit(self, data=None) -> "StorageModel":
        """Learn from data; FIFO and mixing have nothing to learn."""
        return self

    def bind(self, particles, owner: int) -> "StorageModel":
        """Attach to a particle store and the storage asset's owner index."""
        self.particles = particles
        self.owner = int(owner)
        return self

    def receive(self, ids, t: float) -> None:
        """Particles (already owned by this storage) enter at time ``t``."""
        raise NotImplementedError

    def held_ids(self) -> np.ndarray:
        """Ids of the particles held, in the model's order of leaving."""
        raise NotImplementedError

    def held_mass(self) -> float:
        """Mass held [kg]."""
        return self.particles.total_mass(self.owner)

    def step(self, t: float, dt: float, discharge_rate: float) -> np.ndarray:
        """Advance ``dt`` [s]; return the ids that leave through the outlet."""
        rate = check_discharge_rate(discharge_rate)
        order = self.held_ids()
        if order.size == 0:
            self._credit_kg = 0.0
            return order
        self._credit_kg += rate * dt
        # Only the head of the queue can leave in one step: look at a prefix
        # that grows until its mass exceeds the credit (O(leaving), not O(held)).
        head = 64
        while True:
            masses = self.particles.mass[self.particles.slots(order[:head])]
            if head >= order.size or masses.sum() > self._credit_kg:
                break
            head *= 4
        count = int(np.searchsorted(np.cumsum(masses), self._credit_kg, side="right"))
        self._credit_kg -= float(masses[:count].sum())
        leaving = order[:count]
        self._forget(leaving)
        return leaving

    def predict(self, horizon: float, discharge_rate: float):
        """``(ids, mass_kg)`` expected to leave within ``horizon`` seconds."""
        rate = check_discharge_rate(discharge_rate)
        order = self.held_ids()
        masses = self.particles.mass[self.particles.slots(order)]
        budget = self._credit_kg + rate * horizon
        before = np.cumsum(masses) - masses
        share = np.clip(budget - before, 0.0, masses)
        keep = share > 0
        return order[keep], share[keep]

    def _forget(self, ids: np.ndarray) -> None:
        raise NotImplementedError


class FifoStorage(StorageModel):
    """Plug flow: first in, first out (Wambeke et al. 2018's stockpile model).

    The held particles form a queue in arrival order; the feeder takes the
    oldest first.
    """

    name = "fifo"

    def __init__(self):
        super().__init__()
        self._queue = np.empty(0, dtype=np.uint64)

    def receive(self, ids, t: float) -> None:
        self._queue = np.concatenate((self._queue, np.asarray(ids, dtype=np.uint64)))

    def held_ids(self) -> np.ndarray:
        return self._queue

    def _forget(self, ids: np.ndarray) -> None:
        self._queue = self._queue[ids.size:]


class MixingStorage(StorageModel):
    """Perfect mixing: every held kilogram is equally likely to leave next.

    The order of leaving is a mass-weighted random permutation drawn with
    the scenario's generator: each particle gets an exponential clock with
    rate m (the Efraimidis-Spirakis key -log(u)/m) and particles leave in
    clock order, so the next to leave is particle i with probability
    m_i / sum m. The clocks are memoryless, so an arrival gets its clock
    after the last one that left (now + E/m) and is merged into the order
    in O(held) instead of redrawing every key: the outflow composition
    equals the storage composition in expectation at every moment.

    Parameters
    ----------
    rng : numpy.random.Generator
        The scenario's seeded generator (determinism).
    """

    name = "mixing"

    def __init__(self, rng: np.random.Generator | None = None):
        super().__init__()
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self._order = np.empty(0, dtype=np.uint64)
        self._clock = np.empty(0)        # leaving clock of each held particle, ascending
        self._now = 0.0                  # clock of the last particle that left

    def receive(self, ids, t: float) -> None:
        ids = np.asarray(ids, dtype=np.uint64)
        masses = self.particles.mass[self.particles.slots(ids)]
        clocks = self._now + self.rng.standard_exponential(ids.size) / masses
        arrival = np.argsort(clocks, kind="stable")
        at = np.searchsorted(self._clock, clocks[arrival], side="right")
        self._clock = np.insert(self._clock, at, clocks[arrival])
        self._order = np.insert(self._order, at, ids[arrival])

    def held_ids(self) -> np.ndarray:
        return self._order

    def predict(self, horizon: float, discharge_rate: float):
        """Perfect mixing predicts the storage composition: every particle
        contributes in proportion to its mass."""
        rate = check_discharge_rate(discharge_rate)
        ids = self._order
        masses = self.particles.mass[self.particles.slots(ids)]
        held = masses.sum()
        if held <= 0:
            return ids, masses
        fraction = min((self._credit_kg + rate * horizon) / held, 1.0)
        return ids, masses * fraction

    def _forget(self, ids: np.ndarray) -> None:
        if ids.size:
            self._now = float(self._clock[ids.size - 1])
        self._clock = self._clock[ids.size:]
        self._order = self._order[ids.size:]


STORAGE_MODELS: dict[str, str] = {
    "fifo": "cosim.storage:FifoStorage",
    "mixing": "cosim.storage:MixingStorage",
    "rom": "surrogate.rom.storage:RomStorage",
    "dem": "surrogate.dem_storage:DemStorage",
}
"""Storage models by name, cheapest first; values are ``module:Class``."""


def storage_class(name: str, field: str = "storage_model") -> type:
    """The class of the storage model registered as ``name``."""
    if name not in STORAGE_MODELS:
        raise ValidationError(field, f"one of {list(STORAGE_MODELS)}", f"got {name!r}")
    module, cls = STORAGE_MODELS[name].split(":")
    return getattr(importlib.import_module(module), cls)


def check_storage_options(name: str, options: dict, field: str = "options") -> None:
    """Refuse keyword options that the storage model ``name`` does not take, naming them."""
    import inspect

    accepted = [p for p, spec in inspect.signature(storage_class(name)).parameters.items()
                if spec.kind in (spec.KEYWORD_ONLY, spec.POSITIONAL_OR_KEYWORD)
                and p not in ("self", "rng")]
    for key in options:
        if key not in accepted:
            raise ValidationError(f"{field}.{key}", f"an option of the {name!r} storage model: "
                                  f"one of {accepted}" if accepted else
                                  f"absent: the {name!r} storage model takes no options",
                                  "unknown option")


def make_storage(name: str, **options) -> StorageModel:
    """Build the storage model called ``name`` with keyword ``options``."""
    cls = storage_class(name)
    check_storage_options(name, {k: v for k, v in options.items() if k != "rng"})
    return cls(**options)
