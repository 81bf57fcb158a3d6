"""Storage models (stockpile, bin, chute) behind one interface.

Source: paper sections "Introduction" and "Digital twin as a distributed
particle simulation": micro-tracking in chutes, silos and stockpiles needs a
model "that may range from simple first-in-first-out or perfect mixing
models, to a physics-based flow model"; they form a fidelity ladder
(docs/architecture.md): plug flow (FIFO) < perfect mixing < reduced-order model
(ROM) < DEM.

Every model has the same calls (scikit-learn style: ``__init__`` stores
parameters, a model that reads a trained state from a file does it in
``load``):

``Model(**options, rng=generator)``
    every model takes the keyword ``rng``, a ``numpy.random.Generator``: the
    one seeding rule. Same generator state, same result. A model that draws
    nothing ignores it.
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
    leave (paper section "Predicting the properties of the mill feed");
    ``predict_each(horizons, discharge_rate)`` gives it for several horizons.

Capabilities are class attributes with defaults on ``StorageModel``
(``has_geometry``, ``checkpointable``, ``arrivals_join_the_tail``), read from
the class, never probed.

Models are registered through the entry-point group ``minetwin.storage``
(``[project.entry-points."minetwin.storage"]`` in a package's pyproject: name
= ``"module:Class"``); MineTwin's own models are registered the same way as a
third party's. ``storage_class(name)`` loads the class of a registered name
(importing it only then), ``make_storage(name, rng=..., **options)`` builds one.
"""

from __future__ import annotations

import numpy as np

from cosim.errors import ValidationError
from cosim.plugins import load_registered, registered

MAX_DISCHARGE_RATE = 2000.0
"""Largest feeder rate [kg/s] (paper: up to 2 t/s)."""


def check_discharge_rate(rate: float, limit: float = MAX_DISCHARGE_RATE) -> float:
    """Refuse a discharge rate outside [0, limit] kg/s."""
    rate = float(rate)
    if not np.isfinite(rate) or rate < 0 or rate > limit:
        raise ValidationError("discharge_rate", f"in [0, {limit:g}] kg/s", f"got {rate!r}")
    return rate


def budget_shares(order: np.ndarray, masses: np.ndarray, budget_kg: float):
    """``(ids, mass_kg)``: the particles ``order`` (ids in their order of leaving,
    of ``masses`` [kg]) that a feeder budget of ``budget_kg`` [kg] draws, the last
    one in part."""
    share = np.clip(budget_kg - (np.cumsum(masses) - masses), 0.0, masses)
    keep = share > 0
    return order[keep], share[keep]


class StorageModel:
    """Base class: bookkeeping shared by every storage model.

    A queue-like subclass implements ``receive``, ``held_ids`` (the held
    particles in the order they will leave) and ``_forget`` (drop the head
    of that order); the base class runs the feeder's mass credit in ``step``
    and the prediction in ``predict``. A model with its own flow (ROM, DEM)
    overrides ``step`` and ``predict`` as well.

    Parameters
    ----------
    rng : numpy.random.Generator, optional
        The model's seeded generator (default ``default_rng(0)``); kept as
        ``self.rng``.
    """

    name = "base"

    has_geometry = False
    """True: the model places its held particles itself in the x-y plane of the
    pile (``position[:, 0]`` = x horizontal, ``position[:, 1]`` = y up [m]) and
    sets their velocities [m/s]; views show them there. False: views draw the
    schematic layout of the order of leaving (``cosim.storage_view``)."""

    checkpointable = False
    """True: the model's state is plain data (numbers, numpy arrays and
    generators, containers, objects of registered or project classes), so the
    stockpile client's checkpoint can save and restore it exactly."""

    arrivals_join_the_tail = False
    """True: an arrival goes behind every held particle in the order of leaving
    and changes nothing ahead of it (a queue: FIFO). Then, over an interval in
    which the feeder's credit (``feeder_credit_kg`` + rate x length) stays below
    the mass held at its start, no arrival of the interval can leave and the
    pile never runs empty, so the interval's arrivals received together and one
    ``step`` over it take exactly the particles that stepping to each arrival
    in turn would (the credit's prefix of the same order): the stockpile
    client catches up that way, one step per slice instead of per bin."""

    default_model_file = None
    """For a trained model: the file it loads when given none (a ``pathlib.Path``),
    so that a fidelity card measured on that file (its SHA-256 in the card's
    provenance) counts for a stockpile that names no file; None otherwise."""

    out_of_range_now: tuple[str, ...] = ()
    """Names of the inputs outside the model's range of validity at its latest
    check (a ROM's training ranges); always empty for a model without one."""

    def __init__(self, *, rng: np.random.Generator | None = None):
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.particles = None
        self.owner = None
        self._credit_kg = 0.0

    def bind(self, particles, owner: int) -> "StorageModel":
        """Attach to a particle store and the storage asset's owner index."""
        self.particles = particles
        self.owner = int(owner)
        return self

    def receive(self, ids, t: float) -> None:
        """Particles (already owned by this storage) enter at time ``t``."""
        raise NotImplementedError

    def prefill(self, ids, t: float) -> None:
        """Particles the pile held before the run began (earlier production), at
        time ``t``: by default received as any arrival. A model with geometry may
        lay them at once as its inlet would have built the pile, at rest; they are
        no part of its inflow."""
        self.receive(ids, t)

    def held_ids(self) -> np.ndarray:
        """Ids of the particles held, in the model's order of leaving."""
        raise NotImplementedError

    def bulk_areal_density(self) -> float | None:
        """Mass per area of the pile's x-y section [kg/m^2] for a model with
        geometry (how densely a hand-over from a model without it lays the pile
        out, ``cosim.handover``); None without geometry."""
        return None

    @property
    def feeder_credit_kg(self) -> float:
        """Mass [kg] the feeder is owed: commanded but not yet drawn as whole particles."""
        return self._credit_kg

    def adopt(self, ids, t: float, *, positions=None, credit_kg: float = 0.0) -> None:
        """Take over, at time ``t`` [s], a pile another storage model held (a
        hand-over along the fidelity ladder, ``cosim.handover``): ``ids`` in that
        model's order of leaving, their x-y ``positions`` [m] if it had geometry
        (None otherwise), and the feeder's mass credit [kg], which carries over
        so that the outflow stays exact. The particles are already owned by this
        storage. By default they are received in that order (a queue keeps it;
        perfect mixing draws their clocks); a model with geometry places them."""
        self.receive(ids, t)
        self._credit_kg = float(credit_kg)

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
        return budget_shares(order, masses, self._credit_kg + rate * horizon)

    def predict_each(self, horizons, discharge_rate: float) -> list:
        """``predict`` for each of ``horizons`` [s] (a profile of the feed). A model
        whose forecast is costly (the ROM runs its flow forward) overrides this to
        read every horizon from one forecast."""
        return [self.predict(horizon, discharge_rate) for horizon in horizons]

    def _forget(self, ids: np.ndarray) -> None:
        raise NotImplementedError


class FifoStorage(StorageModel):
    """Plug flow: first in, first out (Wambeke et al. 2018's stockpile model).

    The held particles form a queue in arrival order; the feeder takes the
    oldest first.
    """

    name = "fifo"
    checkpointable = True
    arrivals_join_the_tail = True

    def __init__(self, *, rng: np.random.Generator | None = None):
        super().__init__(rng=rng)
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
        The seeded generator of the clocks (determinism; default seed 0).
    """

    name = "mixing"
    checkpointable = True

    def __init__(self, *, rng: np.random.Generator | None = None):
        super().__init__(rng=rng)
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


ENTRY_POINT_GROUP = "minetwin.storage"
"""Entry-point group of the storage models: name = ``"module:Class"``."""


def registered_models() -> dict:
    """The registered storage models: name -> entry point (not yet imported), by name."""
    return registered(ENTRY_POINT_GROUP)


def storage_class(name: str, field: str = "storage_model") -> type:
    """The class of the storage model registered as ``name`` (imported now)."""
    models = registered_models()
    if name not in models:
        raise ValidationError(field, f"one of {list(models)} (the registered storage models)",
                              f"got {name!r}")
    cls = load_registered(models[name], field, "a storage model")
    if not (isinstance(cls, type) and issubclass(cls, StorageModel)):
        raise ValidationError(field, "a subclass of cosim.storage.StorageModel",
                              f"{name!r} is registered as {models[name].value}")
    return cls


def storage_options(name: str) -> list[str]:
    """The keyword options the storage model ``name`` takes (``rng`` aside: it is
    the seeding rule, given by the caller)."""
    import inspect

    return [p for p, spec in inspect.signature(storage_class(name)).parameters.items()
            if spec.kind in (spec.KEYWORD_ONLY, spec.POSITIONAL_OR_KEYWORD)
            and p not in ("self", "rng")]


def check_storage_options(name: str, options: dict, field: str = "options") -> None:
    """Refuse keyword options that the storage model ``name`` does not take, naming them."""
    accepted = storage_options(name)
    for key in options:
        if key not in accepted:
            raise ValidationError(f"{field}.{key}", f"an option of the {name!r} storage model: "
                                  f"one of {accepted}" if accepted else
                                  f"absent: the {name!r} storage model takes no options",
                                  "unknown option")


def make_storage(name: str, *, rng: np.random.Generator | None = None,
                 **options) -> StorageModel:
    """Build the storage model called ``name`` with keyword ``options``, seeded by ``rng``."""
    cls = storage_class(name)
    check_storage_options(name, options)
    return cls(rng=rng, **options)
