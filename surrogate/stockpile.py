"""The stockpile asset of the integration test: particles in, storage model, outflow.

Source: paper section "Integration test": "Each bin on the incoming conveyor
contain material with a specific mass, ore grade and a tracking-id. [...]
The storage asset responds by emitting particles with the corresponding
total mass and mineral concentration. [...] The storage asset receives a
discharge rate control signal [...] The particles that reach the outlet are
eliminated and a macro-tracking message is passed so that the [...]
simulator receive information of the material that enters the outgoing
conveyer. That information include tracking-ids, mass and ore grade."

The asset owns its own ``ParticleStore`` and a storage model picked by name
(``cosim.storage.make_storage``: any registered model, ``fifo``, ``mixing``,
``rom``, ``dem`` or a plug-in's), seeded by the asset's generator. Every particle carries the inbound bin's tracking id as the
uint64 extrinsic attribute ``tracking_id`` and its source index as ``source``.

What the asset shows (totals, fields, particle table, predicted feed, layout)
is ``cosim.stockpile_view``, the same functions the mine simulator's REST view
calls: a model without geometry (FIFO, mixing) is drawn in the schematic half
disc of radius ``pile_radius_m``, a model with ``has_geometry`` (ROM, DEM) at its
own positions; ``origin`` is the source index of the inbound bin.

Parameters (``StockpileAsset``)
-------------------------------
model : str
    Storage model name, default ``"fifo"``.
seed : int
    Seed of the asset's generator, which the storage model draws from (its
    ``rng``), default 0.
particle_mass_kg : float
    Target pseudo-particle mass [kg], default 100 (paper: ~100 kg each);
    a bin of mass m becomes ceil(m / particle_mass_kg) equal particles.
feed_size_m : float
    Characteristic size x_c [m] of the Rosin-Rammler distribution given to
    the crushed feed's particles, default 0.05.
pile_radius_m : float
    Radius [m] of the schematic display pile, default 10.
history_rows : int
    How many per-step totals rows ``history`` keeps, default 100000.
source_names : dict or None
    Display name of each source index (``{0: "ore body A"}``), shown by the
    monitor's origin key; default None ("source N").
event_rows : int
    How many macro-tracking events (lots in and out) ``events`` keeps,
    default 20000.
"""

from __future__ import annotations


import numpy as np

from cosim import stockpile_view as view
from cosim.errors import ValidationError, check_finite_range
from cosim.particles import ParticleStore
from cosim.sizes import rosin_rammler
from cosim.storage import check_discharge_rate, make_storage
from surrogate.lots import ColumnRing, DischargeRate, LotLog

STOCKPILE_OWNER = 1
"""Owner index of the stockpile in its own particle store."""

TOTALS = ("time_s", "held_mass_kg", "grade", "hardness", "d80_m", "particle_count",
          "discharge_rate_kg_s", "discharge_actual_kg_s")
"""The keys of ``totals()``, one column each of the history."""


class StockpileAsset:
    """Stockpile: inbound bins become particles; the storage model decides
    which particles the feeder takes; outflow is aggregated per tracking id.

    Attributes
    ----------
    time : float
        Simulation time [s].
    discharge_rate : float
        Feeder rate [kg/s] used by the next ``step``.
    particles : ParticleStore
        The particles held (only the stockpile's: leaving ones are removed).
    storage : StorageModel
        The storage model (``fifo``, ``mixing``, ``rom``, ``dem``, ...).
    """

    def __init__(self, model: str = "fifo", *, seed: int = 0, particle_mass_kg: float = 100.0,
                 feed_size_m: float = 0.05, pile_radius_m: float = 10.0,
                 history_rows: int = 100_000, storage_options: dict | None = None,
                 source_names: dict | None = None, event_rows: int = 20_000):
        self.particle_mass_kg = float(check_finite_range(
            "particle_mass_kg", particle_mass_kg, 0.0, low_open=True, unit="kg"))
        self.pile_radius_m = float(check_finite_range(
            "pile_radius_m", pile_radius_m, 0.0, low_open=True, unit="m"))
        self.model_name = model
        self.rng = np.random.default_rng(seed)
        self.storage = make_storage(model, rng=self.rng, **(storage_options or {}))
        self.particles = ParticleStore(capacity=4096, first_id=1)
        self.particles.add_attribute("tracking_id", np.uint64, 0)
        self.particles.add_attribute("source", np.int64, -1)
        self.storage.bind(self.particles, STOCKPILE_OWNER)
        self.feed_f = rosin_rammler(feed_size_m)
        self.time = 0.0
        self.started = False
        """False until the first ``step``: bins received before it are the pile's
        initial inventory (``StorageModel.prefill``)."""
        self.discharge_rate = 0.0
        self.mass_in_kg = 0.0
        self.mass_out_kg = 0.0
        self.discharge_actual = 0.0
        self._actual = DischargeRate(self.time)
        self.source_names = {int(k): str(v) for k, v in (source_names or {}).items()}
        self.lots = LotLog(event_rows)
        self._history = ColumnRing(history_rows, {name: np.int64 if name == "particle_count"
                                                  else np.float64 for name in TOTALS})

    # --------------------------------------------------------------- inflow
    def receive_bin(self, tracking_id: int, mass_kg: float, grade: float, hardness: float,
                    source: int = -1) -> np.ndarray:
        """Emit the particles of one inbound bin at the current time; return their ids.

        The bin is validated whole before anything is added (bad mass,
        grade or hardness raise ``ValidationError`` naming the field).
        """
        mass_kg = float(check_finite_range("mass", mass_kg, 0.0, low_open=True, unit="kg"))
        check_finite_range("grade", grade, 0.0, 1.0)
        check_finite_range("hardness", hardness, 0.0, low_open=True)
        if int(tracking_id) < 0 or int(tracking_id) >= 2**64:
            raise ValidationError("tracking_id", "an unsigned 64-bit integer", f"got {tracking_id}")
        count = max(int(np.ceil(mass_kg / self.particle_mass_kg - 1e-9)), 1)
        masses = np.full(count, mass_kg / count)
        masses[-1] = mass_kg - masses[:-1].sum()  # the bin's mass exactly
        ids = self.particles.add(
            mass=masses, f=self.feed_f, grade=grade, hardness=hardness,
            owner=STOCKPILE_OWNER, time=self.time,
            tracking_id=np.uint64(tracking_id), source=int(source))
        self._arrive(ids, self.time)
        self.mass_in_kg += mass_kg
        self.lots.add("in", self.time, [int(tracking_id)], [mass_kg], [float(grade)],
                      [int(source)], [count])
        return ids

    def receive_bins(self, tracking_ids, masses_kg, grades, hardness, sources,
                     times_s) -> np.ndarray:
        """Emit the particles of several inbound bins, each at its own time
        ``times_s`` [s] (none before ``time``: bins that arrive during the next
        ``step``), in the order given; return their ids.

        The same particles, times and events as ``receive_bin`` per bin, in
        one batch for the store, the storage model and the event log (no
        per-bin Python work). All bins are validated before anything is added.
        Only exact for a model whose arrivals join the tail, over a step the
        feeder cannot reach them in (``cosim.storage.StorageModel``).
        """
        masses = check_finite_range("mass", np.asarray(masses_kg, dtype=np.float64), 0.0,
                                    low_open=True, unit="kg")
        check_finite_range("grade", np.asarray(grades, dtype=np.float64), 0.0, 1.0)
        check_finite_range("hardness", np.asarray(hardness, dtype=np.float64), 0.0,
                           low_open=True)
        tids = np.asarray(tracking_ids)
        if tids.size and (tids.dtype.kind not in "iu" or int(tids.min()) < 0):
            raise ValidationError("tracking_id", "unsigned 64-bit integers", f"got {tids.min()}")
        times = check_finite_range("times_s", np.asarray(times_s, dtype=np.float64), self.time,
                                   unit="s")
        if masses.size == 0:
            return np.empty(0, dtype=np.uint64)
        counts = np.maximum(np.ceil(masses / self.particle_mass_kg - 1e-9).astype(np.int64), 1)
        each = np.repeat(masses / counts, counts)
        last = np.cumsum(counts) - 1
        # the last particle of a bin takes the rest: the bin's mass exactly
        each[last] = masses - np.bincount(np.repeat(np.arange(masses.size), counts),
                                          weights=each, minlength=masses.size) + each[last]
        ids = self.particles.add(
            mass=each, f=self.feed_f, grade=np.repeat(grades, counts),
            hardness=np.repeat(hardness, counts), owner=STOCKPILE_OWNER,
            time=np.repeat(times, counts),
            tracking_id=np.repeat(tids.astype(np.uint64), counts),
            source=np.repeat(np.asarray(sources, dtype=np.int64), counts))
        self._arrive(ids, float(times[-1]))
        self.mass_in_kg += float(masses.sum())
        self.lots.add("in", times, tids.astype(np.uint64), masses,
                      np.asarray(grades, dtype=np.float64), np.asarray(sources, dtype=np.int64),
                      counts)
        return ids

    def _arrive(self, ids: np.ndarray, t: float) -> None:
        # bins that come before the first step are what the pile held when the
        # plant started (the mock 800xA's sp201.initial_inventory_kg)
        if self.started:
            self.storage.receive(ids, t)
        else:
            self.storage.prefill(ids, t)

    # ----------------------------------------------------------------- step
    def set_discharge_rate(self, rate_kg_s: float) -> None:
        """Feeder setpoint [kg/s] in [0, 2000]."""
        self.discharge_rate = check_discharge_rate(rate_kg_s)

    def step(self, dt: float) -> dict:
        """Advance ``dt`` [s]; remove the particles that reach the outlet.

        Returns the outflow aggregated per tracking id: ``tracking_ids``
        (uint64), ``masses`` [kg], ``grades`` (mass-weighted), ``sources``
        and ``particle_ids`` of the removed particles.
        """
        dt = float(check_finite_range("dt", dt, 0.0, unit="s"))
        self.started = True
        leaving = self.storage.step(self.time, dt, self.discharge_rate)
        self.time += dt
        outflow = self._remove(leaving)
        self.discharge_actual = self._actual.add(self.time, float(outflow["masses"].sum()))
        self.lots.add("out", self.time, outflow["tracking_ids"], outflow["masses"],
                      outflow["grades"], outflow["sources"], outflow["counts"])
        self._history.append(**self.totals())
        return outflow

    def _remove(self, ids: np.ndarray) -> dict:
        store = self.particles
        if ids.size == 0:  # most steps of a slow feeder: nothing reaches the outlet
            empty = np.empty(0)
            return {"tracking_ids": np.empty(0, dtype=np.uint64), "masses": empty,
                    "grades": empty, "sources": np.empty(0, dtype=np.int64),
                    "counts": np.empty(0, dtype=np.int64),
                    "particle_ids": np.empty(0, dtype=np.uint64)}
        slots = store.slots(ids)
        tids = store.attribute("tracking_id")[slots]
        mass = store.mass[slots]
        grade = store.grade[slots]
        source = store.attribute("source")[slots]
        unique, first, inverse = np.unique(tids, return_index=True, return_inverse=True)
        out_mass = np.bincount(inverse, weights=mass, minlength=unique.size).astype(np.float64)
        out_grade = np.bincount(inverse, weights=mass * grade,
                                minlength=unique.size).astype(np.float64)
        out_grade = np.divide(out_grade, out_mass, out=np.zeros_like(out_mass), where=out_mass > 0)
        counts = np.bincount(inverse, minlength=unique.size)
        store.remove_slots(slots)
        self.mass_out_kg += float(mass.sum())
        return {"tracking_ids": unique.astype(np.uint64), "masses": out_mass,
                "grades": np.clip(out_grade, 0.0, 1.0), "sources": source[first],
                "counts": counts, "particle_ids": np.asarray(ids, dtype=np.uint64)}

    # ------------------------------------------------------------- sensors
    def held_by_tracking_id(self) -> dict[int, float]:
        """Mass [kg] held per tracking id."""
        tids = self.particles.attribute("tracking_id")
        unique, inverse = np.unique(tids, return_inverse=True)
        mass = np.bincount(inverse, weights=self.particles.mass,
                           minlength=unique.size).astype(np.float64)
        return {int(t): float(m) for t, m in zip(unique, mass)}

    def totals(self) -> dict:
        """Virtual sensors over the whole pile (``cosim.stockpile_view.totals``)."""
        return view.totals(self.storage, time=self.time, discharge_rate=self.discharge_rate,
                           discharge_actual=self.discharge_actual)

    def history(self, since: float = -np.inf) -> list[dict]:
        """Totals rows recorded after each step with ``time_s > since``."""
        rows = self._history.last(len(self._history))
        keep = rows["time_s"] > since
        columns = [rows[name][keep].tolist() for name in TOTALS]
        return [dict(zip(TOTALS, values)) for values in zip(*columns)]

    def events(self, since: int = 0) -> list[dict]:
        """Macro-tracking events (lots in and out) with ``seq > since``."""
        return self.lots.since(since)

    @property
    def layout(self) -> str:
        """``particles`` (the model's own positions) or ``schematic``."""
        return view.layout(self.storage)

    def origin_names(self) -> dict:
        """Display name per origin (the source index) of the particles held."""
        return view.origin_names(self.storage, self.source_names)

    def fields(self, nx: int = 32, ny: int = 16) -> dict:
        """Spatial fields on an ny x nx grid over the pile (``cosim.stockpile_view.fields``)."""
        return view.fields(self.storage, nx, ny, time=self.time,
                           discharge_rate=self.discharge_rate, radius=self.pile_radius_m)

    def particle_table(self, limit: int = 1000, offset: int = 0) -> dict:
        """Rows ``offset .. offset+limit`` of the held particles by id
        (``cosim.stockpile_view.particle_table``; ``origin``: the source index)."""
        return view.particle_table(self.storage, limit, offset, time=self.time,
                                   discharge_rate=self.discharge_rate, radius=self.pile_radius_m)

    def predicted_feed(self, horizon_s: float) -> dict:
        """Feed predicted to leave within ``horizon_s`` at the current setpoint
        (``cosim.stockpile_view.predicted_feed``)."""
        return view.predicted_feed(self.storage, horizon_s, self.discharge_rate)

    def predicted_feeds(self, horizons_s) -> list[dict]:
        """``predicted_feed`` for each of ``horizons_s`` [s], from one forecast
        (``cosim.stockpile_view.predicted_feeds``)."""
        return view.predicted_feeds(self.storage, horizons_s, self.discharge_rate)
