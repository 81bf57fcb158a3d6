"""Macro-tracking events and the SQLite event store.

Source: paper section "Digital twin as a distributed particle simulation",
the event message
    event = {id, type, location x, time t, particles = {[n1, X_n1(t)], ...}}
extended with the asset that emits it.

The store is one SQLite file (WAL mode) with two tables:

``events``
    event_id, type, asset, x, y, z [m], time [s], n_particles
``event_particles``
    event_id, particle_id, mass [kg], x, y, z [m], grade [-], hardness [-],
    origin_block, f (the 16 size fractions as a float64 BLOB)

Writes are buffered and inserted in batches; read back as pandas DataFrames
(by particle id, asset, time range or type) and export to Parquet. A store
opened with ``readonly=True`` never writes to its file. Another process holding
the database's lock is waited for up to ``timeout`` seconds; a store that cannot
be written or read raises ``EventStoreError`` naming the file, never an asset.
"""

from __future__ import annotations

import sqlite3
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cosim.errors import ValidationError
from cosim.master import CosimulationError
from cosim.sizes import N_CLASSES

MAX_ID = 2 ** 63 - 1
"""Largest particle id the store holds (SQLite integers are signed 64-bit)."""


class EventStoreError(CosimulationError):
    """The event store's file cannot be written or read (locked, not a database,
    truncated, unwritable); the message names the file."""

    blames_component = False

EVENT_TYPES = ("appear", "load", "dump", "enter", "exit", "pass", "product", "switch")
"""Event types: material appears at a source, is loaded into or dumped from
a vehicle, enters or exits an asset, passes a point (e.g. the jaw), leaves
the plant as product, or is handed over from one storage model to another
inside a stockpile (``cosim.handover``: the pile as it was handed over)."""

PARTICLE_FIELDS = ("mass", "position", "grade", "hardness", "origin_block", "f")
"""Particle state recorded with each event (X_n of the paper, less velocity)."""

_SCHEMA = """
CREATE TABLE IF NOT EXISTS events (
    event_id INTEGER PRIMARY KEY, type TEXT NOT NULL, asset TEXT NOT NULL,
    x REAL, y REAL, z REAL, time REAL NOT NULL, n_particles INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS event_particles (
    event_id INTEGER NOT NULL, particle_id INTEGER NOT NULL, mass REAL NOT NULL,
    x REAL, y REAL, z REAL, grade REAL, hardness REAL, origin_block INTEGER, f BLOB);
"""

_INDEXES = """
CREATE INDEX IF NOT EXISTS ix_event_particles_particle ON event_particles (particle_id);
CREATE INDEX IF NOT EXISTS ix_event_particles_event ON event_particles (event_id);
CREATE INDEX IF NOT EXISTS ix_events_time ON events (time);
"""


@dataclass
class Event:
    """One macro-tracking event.

    ``particles`` is a batch (dict of arrays) holding ``id`` and the fields
    of ``PARTICLE_FIELDS`` for every particle involved.
    """

    id: int
    type: str
    asset: str
    location: tuple[float, float, float]
    time: float
    particles: dict[str, np.ndarray]


class EventStore:
    """SQLite event store (one file, WAL mode, batched inserts).

    Parameters
    ----------
    path : str or Path
        Database file; ``":memory:"`` for a throw-away store.
    batch_rows : int
        Particle rows buffered before an insert (default 50,000).
    readonly : bool
        Open an existing store for reading only (default False): the file is
        never written, and a file that is not an event store is refused.
    timeout : float
        Seconds to wait for another process's lock before failing (default 30 s).
    """

    def __init__(self, path, batch_rows: int = 50_000, *, readonly: bool = False,
                 timeout: float = 30.0):
        self.path = str(path)
        self.readonly = bool(readonly)
        self.timeout = float(timeout)
        self._batch_rows = int(batch_rows)
        self._event_rows: list[tuple] = []
        self._particle_rows: list[tuple] = []
        self._indexed = self.readonly
        with self._errors("open"):
            if self.readonly:
                self._db = self._open_readonly()
            else:
                self._db = sqlite3.connect(self.path, timeout=self.timeout)
                if self.path != ":memory:":
                    self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute("PRAGMA synchronous=NORMAL")
                self._db.executescript(_SCHEMA)
            last = self._db.execute("SELECT MAX(event_id) FROM events").fetchone()[0]
        self._next_event_id = 0 if last is None else last + 1

    def _open_readonly(self):
        file = Path(self.path)
        if not file.is_file():
            raise EventStoreError(f"event store {self.path}: no such file")
        if file.stat().st_size == 0:
            raise EventStoreError(f"event store {self.path}: empty file, not an event store")
        db = sqlite3.connect(f"{file.resolve().as_uri()}?mode=ro", uri=True,
                             timeout=self.timeout)
        tables = {name for (name,) in db.execute(
            "SELECT name FROM sqlite_master WHERE type = 'table'")}
        if not {"events", "event_particles"} <= tables:
            db.close()
            raise EventStoreError(f"event store {self.path}: an SQLite file without the "
                                  "events and event_particles tables, not an event store")
        return db

    @contextmanager
    def _errors(self, action: str):
        """Turn SQLite's errors while doing ``action`` into an ``EventStoreError``."""
        try:
            yield
        except sqlite3.Error as exc:
            hint = (f" (waited {self.timeout:g} s for another process's lock)"
                    if "locked" in str(exc) or "busy" in str(exc) else "")
            raise EventStoreError(f"event store {self.path}: cannot {action}: {exc}{hint}") from exc

    # ----------------------------------------------------------------- write
    def record(self, type: str, asset: str, time: float, particles, slots=None,
               location=(0.0, 0.0, 0.0)) -> int:
        """Record an event about ``slots`` of a ``ParticleStore``; returns the event id."""
        batch = particles.gather(slots, fields=("id",) + PARTICLE_FIELDS)
        return self.record_batch(type, asset, time, batch, location)

    def record_batch(self, type: str, asset: str, time: float, batch: dict,
                     location=(0.0, 0.0, 0.0)) -> int:
        """Record an event about a particle batch (dict with ``id`` and the state fields)."""
        counts = [int(np.asarray(batch["id"]).size)]
        return int(self.record_many([type], [asset], [time], [location], counts, batch)[0])

    def record_many(self, types, assets, times, locations, counts, batch) -> np.ndarray:
        """Record several events at once; returns their event ids.

        Event k is ``types[k]`` by ``assets[k]`` at ``times[k]`` [s] and
        ``locations[k]`` [m] and involves ``counts[k]`` particles: the next
        ``counts[k]`` rows of ``batch`` (the events' particle batches
        concatenated in order). One call per many events keeps the Python
        cost per event small for simulators that emit events every step.
        """
        for type in set(types):
            if type not in EVENT_TYPES:
                raise ValidationError("type", f"one of {list(EVENT_TYPES)}", f"got {type!r}")
        times = np.asarray(times, dtype=np.float64)
        if not np.all(np.isfinite(times)):
            raise ValidationError("time", "finite seconds",
                                  f"got {times[~np.isfinite(times)][0]!r}")
        if self.readonly:
            raise EventStoreError(f"event store {self.path}: opened read-only")
        counts = np.asarray(counts, dtype=np.int64)
        raw_ids = np.asarray(batch["id"])
        if raw_ids.size and (raw_ids.min() < 0 or raw_ids.max() > MAX_ID):
            raise ValidationError("id", f"in [0, {MAX_ID}] (SQLite's signed 64-bit integers)",
                                  f"got {raw_ids.max() if raw_ids.max() > MAX_ID else raw_ids.min()}")
        ids = raw_ids.astype(np.int64)
        if counts.sum() != ids.size:
            raise ValidationError("counts", f"summing to the batch size {ids.size}",
                                  f"sum {int(counts.sum())}")
        event_ids = np.arange(self._next_event_id, self._next_event_id + counts.size)
        self._next_event_id += counts.size
        xyz = np.asarray(locations, dtype=np.float64).reshape(-1, 3)
        self._event_rows.extend(zip(
            event_ids.tolist(), types, assets, xyz[:, 0].tolist(), xyz[:, 1].tolist(),
            xyz[:, 2].tolist(), times.tolist(), counts.tolist()))
        if ids.size:
            pos = np.asarray(batch["position"], dtype=np.float64)
            f = np.ascontiguousarray(batch["f"], dtype=np.float64)
            # each row's 16 fractions as one BLOB: a void view lists them as bytes in one call
            blobs = f.view(np.dtype((np.void, f.shape[-1] * f.itemsize))).ravel().tolist()
            self._particle_rows.extend(zip(
                np.repeat(event_ids, counts).tolist(), ids.tolist(),
                np.asarray(batch["mass"]).tolist(),
                pos[:, 0].tolist(), pos[:, 1].tolist(), pos[:, 2].tolist(),
                np.asarray(batch["grade"]).tolist(), np.asarray(batch["hardness"]).tolist(),
                np.asarray(batch["origin_block"]).tolist(), blobs))
        if len(self._particle_rows) >= self._batch_rows:
            self.flush()
        return event_ids

    def flush(self) -> None:
        """Write buffered events in one transaction."""
        if not self._event_rows and not self._particle_rows:
            return
        with self._errors("write"), self._db:
            self._db.executemany("INSERT INTO events VALUES (?,?,?,?,?,?,?,?)",
                                 self._event_rows)
            self._db.executemany(
                "INSERT INTO event_particles VALUES (?,?,?,?,?,?,?,?,?,?)",
                self._particle_rows)
        self._event_rows.clear()
        self._particle_rows.clear()

    def close(self) -> None:
        """Flush, index and close the file (closed even if the flush fails)."""
        try:
            self.flush()
            self._ensure_indexes()
        finally:
            self._db.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _ensure_indexes(self) -> None:
        # Indexes are built once, after the bulk of the inserts, because
        # maintaining them during inserts halves the write rate.
        if not self._indexed:
            with self._errors("index"):
                self._db.executescript(_INDEXES)
            self._indexed = True

    # ------------------------------------------------------------------ read
    def events(self, *, type: str | None = None, asset: str | None = None,
               t0: float | None = None, t1: float | None = None):
        """Events as a DataFrame, filtered by type, asset and time range [t0, t1)."""
        import pandas as pd

        where, args = self._filters(type, asset, t0, t1, prefix="")
        self.flush()
        with self._errors("read"):
            return pd.read_sql_query(f"SELECT * FROM events{where} ORDER BY event_id",
                                     self._db, params=args)

    def particles(self, *, particle_ids=None, type: str | None = None,
                  asset: str | None = None, t0: float | None = None,
                  t1: float | None = None):
        """Particle states at events, joined with the event columns.

        One row per (event, particle); ``f`` is expanded to ``f0``..``f15``.
        """
        import pandas as pd

        self.flush()
        self._ensure_indexes()
        where, args = self._filters(type, asset, t0, t1, prefix="e.")
        if particle_ids is not None:
            ids = [int(i) for i in np.atleast_1d(particle_ids)]
            bad = [i for i in ids if not 0 <= i <= MAX_ID]
            if bad:
                raise ValidationError("particle_id", f"an integer in [0, {MAX_ID}]",
                                      f"got {bad[0]}")
            self._db.execute("CREATE TEMP TABLE IF NOT EXISTS wanted (particle_id INTEGER)")
            self._db.execute("DELETE FROM wanted")
            self._db.executemany("INSERT INTO wanted VALUES (?)", [(i,) for i in ids])
            where += (" AND " if where else " WHERE ") + \
                "p.particle_id IN (SELECT particle_id FROM wanted)"
        query = ("SELECT e.event_id, e.type, e.asset, e.time, p.particle_id, p.mass, "
                 "p.x, p.y, p.z, p.grade, p.hardness, p.origin_block, p.f "
                 "FROM event_particles p JOIN events e ON e.event_id = p.event_id"
                 f"{where} ORDER BY e.time, e.event_id, p.particle_id")
        with self._errors("read"):
            frame = pd.read_sql_query(query, self._db, params=args)
        blobs = frame.pop("f")
        fractions = (np.frombuffer(b"".join(blobs), dtype=np.float64).reshape(-1, N_CLASSES)
                     if len(blobs) else np.empty((0, N_CLASSES)))
        for k in range(N_CLASSES):
            frame[f"f{k}"] = fractions[:, k]
        return frame

    def history(self, particle_id: int):
        """The full macro-tracking history of one particle, in time order."""
        return self.particles(particle_ids=[particle_id])

    def to_parquet(self, directory) -> tuple[Path, Path]:
        """Export to ``directory/events.parquet`` and ``directory/event_particles.parquet``."""
        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        events_path, particles_path = out / "events.parquet", out / "event_particles.parquet"
        self.events().to_parquet(events_path)
        self.particles().to_parquet(particles_path)
        return events_path, particles_path

    @staticmethod
    def _filters(type, asset, t0, t1, prefix):
        clauses, args = [], []
        for column, op, value in (("type", "=", type), ("asset", "=", asset),
                                  ("time", ">=", t0), ("time", "<", t1)):
            if value is not None:
                clauses.append(f"{prefix}{column} {op} ?")
                args.append(value)
        return (" WHERE " + " AND ".join(clauses) if clauses else ""), args
