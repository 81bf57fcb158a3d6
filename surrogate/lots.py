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

from collections import deque

import numpy as np

ACTUAL_RATE_WINDOW_S = 30.0
"""Trailing window [s] of the actual discharge rate (the virtual sensors' 30 s window)."""

EVENT_KINDS = ("in", "out")
"""``in``: a lot received; ``out``: (part of) a lot discharged."""


class LotLog:
    """The latest ``capacity`` macro-tracking events (see module docstring)."""

    def __init__(self, capacity: int = 20_000):
        self._events: deque[dict] = deque(maxlen=int(capacity))
        self.last_seq = 0

    def add(self, kind: str, time_s: float, tracking_ids, masses, grades, sources,
            counts) -> None:
        """Append one event per tracking id (arrays of equal length; ``None``
        tracking id or source when the storage has none)."""
        if kind not in EVENT_KINDS:
            raise ValueError(f"kind: must be one of {EVENT_KINDS} (got {kind!r})")
        for tid, mass, grade, source, count in zip(tracking_ids, masses, grades, sources,
                                                   counts):
            self.last_seq += 1
            self._events.append({
                "seq": self.last_seq, "time_s": float(time_s), "kind": kind,
                "tracking_id": None if tid is None else int(tid),
                "mass_kg": float(mass),
                "grade": float(grade) if np.isfinite(grade) else None,
                "source": None if source is None or int(source) < 0 else int(source),
                "particle_count": int(count)})

    def since(self, seq: int = 0) -> list[dict]:
        """Events with ``seq`` greater than ``seq``, oldest first."""
        if not self._events or self._events[-1]["seq"] <= seq:
            return []
        first = self._events[0]["seq"]
        return list(self._events)[max(int(seq) - first + 1, 0):]


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
