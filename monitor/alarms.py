"""The monitor's alarms: limits with a dead band on the stockpile's measured values,
and the operator's acknowledgement.

Sources: ANSI/ISA-18.2-2016 "Management of Alarm Systems for the Process
Industries", its alarm state diagram (normal; active and unacknowledged;
active and acknowledged; returned to normal and unacknowledged) and its
clause 10.5.5.2 (the control system provides a dead band); EEMUA 191 for
the level's default dead band (2 % of capacity, as tabulated in exida's
"Why should I use an alarm deadband?"). The grade's default, 0.05
percentage points, is 5 % of a copper ore's 0.5-1.5 % band (EEMUA's
composition value is 1 % of the range).

The monitor server, not the page, keeps the alarms (``AlarmBook``), so they
are the same in every browser and survive a page reload. It reads every
``/history`` row of the stockpile in order (``check_row``), so an alarm's
raise and clear times are the simulation times of the rows that passed the
limits, whatever the polling interval.

A HIGH alarm is raised when its value is above the limit and cleared when
the value is at or below ``limit - dead band``; a LOW alarm is raised below
the limit and cleared at or above ``limit + dead band``. A value inside the
dead band keeps the alarm as it is, so a value hovering at the limit raises
one alarm, not one per crossing. Measured values (unit, and the dead band's
unit, in percentage points):

- fill level: held mass / capacity [% of capacity]; dead band
  ``alarms.level_deadband_pct`` [% of capacity], default 2;
- grade: the pile's mass-weighted grade [%]; dead band
  ``alarms.grade_deadband_pct`` [percentage points], default 0.05; no value
  (and no change of the grade alarms) while the pile is empty.

An occurrence of an alarm moves through these states:

``ACTIVE_UNACK`` -(operator acknowledges)-> ``ACTIVE_ACK`` -(value clears)-> ``CLEARED``
``ACTIVE_UNACK`` -(value clears)-> ``CLEARED_UNACK`` -(operator acknowledges)-> ``CLEARED``

A stockpile restart (its clock goes back) clears the active alarms of the old
run (``cleared_by = "restart"``); an unacknowledged one still waits for the
operator. Each acknowledgement records who (the name the operator gives) and
when (wall clock, UTC, and simulation time). An occurrence's ``raised_s`` and
``cleared_s`` are the simulation times [s] of the rows that raised and
cleared it; ``raised_at`` and ``cleared_at`` the monitor's wall clock (UTC,
ISO 8601) when it checked them, so a monitor started beside a running
stockpile dates the alarms of the rows it catches up on to its start.
"""

from __future__ import annotations

import datetime as _dt

from cosim.errors import ValidationError

ALARMS = (
    # id, name shown, measured value, direction, limit key, dead band key
    ("level_high", "LEVEL HIGH", "fill_pct", "high", "level_high_pct", "level_deadband_pct"),
    ("level_low", "LEVEL LOW", "fill_pct", "low", "level_low_pct", "level_deadband_pct"),
    ("grade_high", "GRADE HIGH", "grade_pct", "high", "grade_high_pct", "grade_deadband_pct"),
    ("grade_low", "GRADE LOW", "grade_pct", "low", "grade_low_pct", "grade_deadband_pct"),
)
"""The alarms on the measured values (``measured_values``) and their config keys."""

UNITS = {"fill_pct": "% of capacity", "grade_pct": "%"}
"""Unit of each measured value."""

CLOSED_KEPT = 200
"""Closed occurrences (``CLEARED``) kept for the list, newest; open ones are never dropped."""

OPERATOR_MAX_CHARS = 64
"""Longest operator name an acknowledgement accepts."""


def measured_values(row: dict, capacity_t: float) -> dict:
    """The values the alarms watch in a totals row of the stockpile's REST interface
    (``held_mass_kg`` [kg], ``grade`` [-] or None): fill [% of capacity], grade [%]."""
    grade = row.get("grade")
    return {"fill_pct": 100.0 * row["held_mass_kg"] / (1000.0 * capacity_t),
            "grade_pct": None if grade is None else 100.0 * grade}


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds").replace(
        "+00:00", "Z")


class AlarmBook:
    """Alarm occurrences of one stockpile, newest last.

    ``error`` is the reason the last read of the stockpile failed (None when it worked).

    Parameters
    ----------
    config : dict
        The monitor's configuration (``monitor.config.load_monitor_config``):
        ``stockpile.capacity_t`` [t] and the ``alarms`` limits and dead bands [%].
    """

    def __init__(self, config: dict):
        self.config = config
        self.occurrences: list[dict] = []
        self.last_time_s: float | None = None
        self.error: str | None = None
        self._active: dict[str, dict] = {}
        self._next_seq = 1

    def limits(self) -> list[dict]:
        """Each alarm's limit and the value at which it clears, in its unit."""
        alarms = self.config["alarms"]
        out = []
        for alarm_id, name, quantity, direction, limit_key, band_key in ALARMS:
            limit, band = alarms[limit_key], alarms[band_key]
            out.append({"id": alarm_id, "name": name, "quantity": quantity,
                        "unit": UNITS[quantity], "direction": direction, "limit": limit,
                        "deadband": band,
                        "clears_at": limit - band if direction == "high" else limit + band})
        return out

    def check_row(self, row: dict) -> None:
        """Raise or clear alarms for one totals row (``time_s`` [s] and the measured values)."""
        time_s = row["time_s"]
        if self.last_time_s is not None and time_s < self.last_time_s:
            self.restarted(time_s)
        self.last_time_s = time_s
        values = measured_values(row, self.config["stockpile"]["capacity_t"])
        for limit in self.limits():
            value = values[limit["quantity"]]
            if value is None:
                continue
            high = limit["direction"] == "high"
            active = self._active.get(limit["id"])
            if active is None and (value > limit["limit"] if high else value < limit["limit"]):
                self._raise(limit, value, time_s)
            elif active is not None and (value <= limit["clears_at"] if high
                                         else value >= limit["clears_at"]):
                self._clear(active, time_s, "value")

    def restarted(self, time_s: float) -> None:
        """The stockpile's clock went back to ``time_s``: the old run's alarms clear."""
        for active in list(self._active.values()):
            self._clear(active, time_s, "restart")

    def _raise(self, limit: dict, value: float, time_s: float) -> None:
        occurrence = {
            "seq": self._next_seq, "id": limit["id"], "name": limit["name"],
            "unit": limit["unit"], "direction": limit["direction"], "limit": limit["limit"],
            "clears_at": limit["clears_at"], "state": "ACTIVE_UNACK", "value": value,
            "raised_s": time_s, "raised_at": _now(), "cleared_s": None, "cleared_at": None,
            "cleared_by": None, "acked_by": None, "acked_at": None, "acked_s": None}
        self._next_seq += 1
        self.occurrences.append(occurrence)
        self._active[limit["id"]] = occurrence
        closed = [o for o in self.occurrences if o["state"] == "CLEARED"]
        for old in closed[:max(0, len(closed) - CLOSED_KEPT)]:
            self.occurrences.remove(old)

    def _clear(self, occurrence: dict, time_s: float, cause: str) -> None:
        occurrence.update(state="CLEARED" if occurrence["state"] == "ACTIVE_ACK"
                          else "CLEARED_UNACK",
                          cleared_s=time_s, cleared_at=_now(), cleared_by=cause)
        del self._active[occurrence["id"]]

    def acknowledge(self, seq, operator) -> list[dict]:
        """Acknowledge occurrence ``seq`` (an int, or ``"all"``: every unacknowledged
        one) for ``operator``; returns the occurrences acknowledged.

        Raises ``ValidationError`` (field ``operator`` or ``seq``) for a bad
        request, ``LookupError`` for an unknown ``seq`` and ``ValueError`` for
        one already acknowledged."""
        if not isinstance(operator, str) or not operator.strip() \
                or len(operator.strip()) > OPERATOR_MAX_CHARS or not operator.isprintable():
            raise ValidationError("operator", f"a name of 1 to {OPERATOR_MAX_CHARS} printable "
                                  "characters", f"got {operator!r}")
        if seq == "all":
            chosen = [o for o in self.occurrences if o["state"] in ("ACTIVE_UNACK",
                                                                    "CLEARED_UNACK")]
        elif isinstance(seq, int) and not isinstance(seq, bool):
            chosen = [o for o in self.occurrences if o["seq"] == seq]
            if not chosen:
                raise LookupError(f"seq: no alarm occurrence {seq} (known: "
                                  f"{[o['seq'] for o in self.occurrences]})")
            if chosen[0]["acked_by"] is not None:
                raise ValueError(f"seq: alarm occurrence {seq} was acknowledged by "
                                 f"{chosen[0]['acked_by']!r} at {chosen[0]['acked_at']}")
        else:
            raise ValidationError("seq", "an alarm occurrence's seq (integer) or \"all\"",
                                  f"got {seq!r}")
        at = _now()
        for occurrence in chosen:
            occurrence.update(acked_by=operator.strip(), acked_at=at, acked_s=self.last_time_s,
                              state="ACTIVE_ACK" if occurrence["state"] == "ACTIVE_UNACK"
                              else "CLEARED")
        return chosen

    def summary(self) -> dict:
        """What ``/monitor/alarms`` serves: the occurrences (oldest first), counts and limits."""
        return {"alarms": self.occurrences, "limits": self.limits(),
                "active": len(self._active),
                "unacknowledged": sum(o["state"] in ("ACTIVE_UNACK", "CLEARED_UNACK")
                                      for o in self.occurrences),
                "checked_s": self.last_time_s}
