"""The stockpile's macro-tracking event list: lots in and lots out, with tracking ids.

Source: paper section "Integration test": "Each bin on the incoming conveyor
contain material with a specific mass, ore grade and a tracking-id [...] a
macro-tracking message is passed so that the [...] simulator receive
information of the material that enters the outgoing conveyer. That
information include tracking-ids, mass and ore grade."

A ``LotLog`` keeps the latest ``capacity`` events in the order they happened,
each numbered by ``seq`` (1, 2, ...; never reused within a run), so that a
reader asks for the events after the last ``seq`` it saw (REST ``/events``).
An event is ``{"seq", "time_s", "kind": "in" | "out", "tracking_id",
"mass_kg", "grade", "source", "particle_count"}``: ``in`` is one inbound
bin; ``out`` is the part of one tracking id that left in one step, so a lot
leaves over one or more ``out`` events. Units: s, kg; grade dimensionless.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

ACTUAL_RATE_WINDOW_S = 30.0
"""Trailing window [s] of the actual discharge rate (the virtual sensors' 30 s window)."""

EVENT_KINDS = ("in", "out")
"""``in``: a lot received; ``out``: (part of) a lot discharged."""


class ColumnRing:
    """The latest ``capacity`` rows of fixed numeric columns, oldest first.

    A ring buffer of one array per column (structure of arrays): appending
    a row writes one element per column, and a checkpoint stores the
    columns as raw arrays instead of a Python object per row. The arrays
    start small and double up to ``capacity`` rows.
    """

    def __init__(self, capacity: int, columns: dict):
        self.capacity = max(int(capacity), 1)
        size = min(self.capacity, 1024)
        self.columns = {name: np.zeros(size, dtype=dtype) for name, dtype in columns.items()}
        self.start = 0
        self.count = 0

    def __len__(self) -> int:
        return self.count

    def append(self, **values) -> None:
        """One row: a scalar per column."""
        self._reserve(self.count + 1)
        size = next(iter(self.columns.values())).size
        slot = (self.start + self.count) % size
        for name, column in self.columns.items():
            column[slot] = values[name]
        self._advance(1, size)

    def extend(self, **values) -> None:
        """Several rows: arrays of equal length per column (only the last
        ``capacity`` rows are kept)."""
        k = len(next(iter(values.values())))
        if k == 0:
            return
        skip = max(k - self.capacity, 0)
        self._reserve(self.count + k - skip)
        size = next(iter(self.columns.values())).size
        slots = (self.start + self.count + np.arange(k - skip)) % size
        for name, column in self.columns.items():
            column[slots] = np.asarray(values[name])[skip:]
        self._advance(k - skip, size)

    def _advance(self, k: int, size: int) -> None:
        overflow = max(self.count + k - self.capacity, 0)
        self.start = (self.start + overflow) % size
        self.count = min(self.count + k, self.capacity)

    def _reserve(self, needed: int) -> None:
        size = next(iter(self.columns.values())).size
        if needed <= size or size >= self.capacity:
            return
        grown = min(max(2 * size, needed), self.capacity)
        order = self._order(self.count)
        for name, column in self.columns.items():
            fresh = np.zeros(grown, dtype=column.dtype)
            fresh[:self.count] = column[order]
            self.columns[name] = fresh
        self.start = 0

    def _order(self, k: int) -> np.ndarray:
        size = next(iter(self.columns.values())).size
        return (self.start + np.arange(self.count - k, self.count)) % size

    def last(self, k: int) -> dict:
        """The latest ``k`` rows (at most all), oldest first, as arrays per column."""
        order = self._order(min(max(int(k), 0), self.count))
        return {name: column[order] for name, column in self.columns.items()}


class LotLog:
    """The latest ``capacity`` macro-tracking events (see module docstring), kept
    as columns (``ColumnRing``); ``since`` builds the event dicts."""

    def __init__(self, capacity: int = 20_000):
        self._rows = ColumnRing(capacity, {
            "time_s": np.float64, "kind": np.int8, "tracking_id": np.uint64,
            "has_tracking_id": np.bool_, "mass_kg": np.float64, "grade": np.float64,
            "source": np.int64, "particle_count": np.int64})
        self.last_seq = 0

    def add(self, kind: str, time_s: float, tracking_ids, masses, grades, sources,
            counts) -> None:
        """Append one event per tracking id (arrays of equal length; ``None``
        tracking id or source when the storage has none); ``time_s`` is one
        time or one per event."""
        if kind not in EVENT_KINDS:
            raise ValueError(f"kind: must be one of {EVENT_KINDS} (got {kind!r})")
        tids, sources = np.asarray(tracking_ids), np.asarray(sources)
        k = tids.size
        if k == 0:
            return
        if tids.dtype.kind in "iu":
            has = np.ones(k, dtype=bool)
        else:  # None where the storage has no tracking id
            has = np.array([t is not None for t in tids.tolist()])
            tids = np.array([int(t) if t is not None else 0 for t in tids.tolist()])
        if sources.dtype.kind not in "iu":
            sources = np.array([-1 if s is None else int(s) for s in sources.tolist()])
        self._rows.extend(
            time_s=np.broadcast_to(np.asarray(time_s, dtype=np.float64), (k,)),
            kind=np.full(k, EVENT_KINDS.index(kind)),
            tracking_id=tids.astype(np.uint64), has_tracking_id=has,
            mass_kg=masses, grade=grades, source=sources, particle_count=counts)
        self.last_seq += k

    def since(self, seq: int = 0) -> list[dict]:
        """Events with ``seq`` greater than ``seq``, oldest first."""
        rows = self._rows.last(self.last_seq - max(int(seq), 0))
        first = self.last_seq - len(rows["time_s"]) + 1
        return [{"seq": first + k, "time_s": t, "kind": EVENT_KINDS[kind],
                 "tracking_id": tid if has else None, "mass_kg": m,
                 "grade": g if math.isfinite(g) else None,
                 "source": None if src < 0 else src, "particle_count": n}
                for k, (t, kind, tid, has, m, g, src, n) in enumerate(zip(
                    *(rows[c].tolist() for c in ("time_s", "kind", "tracking_id",
                                                 "has_tracking_id", "mass_kg", "grade",
                                                 "source", "particle_count"))))]


class DischargeRate:
    """The actual discharge rate [kg/s]: the mass that left in the trailing
    ``window_s`` [s] (default 30) over that window, or over the time since
    ``start_s`` while the run is younger than the window. A per-step rate of
    ~100 kg pseudo-particles jumps by a particle per step; the window
    averages that out like the other virtual sensors."""

    def __init__(self, start_s: float = 0.0, window_s: float = ACTUAL_RATE_WINDOW_S):
        self.start_s = float(start_s)
        self.window_s = float(window_s)
        self._left: deque[tuple[float, float]] = deque()
        self._sum = 0.0

    def add(self, time_s: float, mass_kg: float) -> float:
        """Record ``mass_kg`` leaving at ``time_s``; returns the rate then."""
        self._left.append((float(time_s), float(mass_kg)))
        self._sum += float(mass_kg)
        while self._left and self._left[0][0] <= time_s - self.window_s:
            self._sum -= self._left.popleft()[1]
        span = min(self.window_s, time_s - self.start_s)
        return max(self._sum, 0.0) / span if span > 0 else 0.0
