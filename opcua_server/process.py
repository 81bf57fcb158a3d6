"""Process simulation of the mock 800xA plant: CV101 -> SP201 -> CV301.

Source: paper section "Integration test": "The ABB simulator represent the
assets of the incoming and outgoing conveyors, discretized in bins moving
with the controlled conveyor belt speed. Each bin on the incoming conveyor
contain material with a specific mass, ore grade and a tracking-id. That
information is exchanged with the stockpile asset when a bin reach the
discharge point."

Model
-----
A belt of length L [m] holds n = round(L / b) bins of length b [m]; slot 0
is the loading point, slot n-1 the discharge point. The belt advances by
v dt [m]; every time it has advanced one bin length the bins shift by one
slot. On CV101 the bin leaving slot n-1 is discharged onto the stockpile
and becomes an *inbound record*; the new bin at slot 0 is filled by the feed
schedule with mass  m = q b / v  (q: the lot's feed rate [kg/s], v: belt
speed [m/s]), the lot's grade, hardness and source, and the next tracking id.
On CV301 the bin at slot 0 collects the outflow the stockpile reports; it
moves on with the belt and is delivered at the end.

Exchange (the part that must lose nothing)
------------------------------------------
* Inbound: every record gets the next sequence number and stays *pending*
  until the stockpile acknowledges a sequence number >= its own.
* Outbound: ``report_outflow(sequence, tracking_ids, masses, grades)`` is
  applied once per sequence number: a repeat of an applied number is
  answered "already applied" without effect; a gap is refused.
* Every refusal raises ``ExchangeRefused(status, field, message)`` before
  any state changes.

Parameters come from the configuration (``opcua_server.config``); units SI.
"""

from __future__ import annotations

import hashlib
from collections import deque
from dataclasses import dataclass

import numpy as np

from cosim.errors import ValidationError

MASS_TOLERANCE = 1e-9
"""Relative slack [-] when checking a tracking id's outflow against its inflow
(the stockpile splits a bin into particles; float sums differ in the last bits)."""


FLOW_WINDOW_S = 10.0
"""Plant time [s] over which the belt scales average the mass flow."""

SETPOINT_CHANGES_KEPT = 64
"""How many of the latest setpoint changes the plant publishes (with the plant
time each took effect), enough for a client many cycles behind."""

MAX_REPORT_ROWS = 10_000
"""Most tracking ids [-] in one outflow report; the stockpile reports one cycle's
outflow (a few particles per tracking id), far below this."""


def report_digest(tracking_ids: np.ndarray, masses: np.ndarray, grades: np.ndarray) -> str:
    """SHA-256 of an outflow report's contents (tells a resend from a conflict)."""
    digest = hashlib.sha256()
    for arr, dtype in ((tracking_ids, "<u8"), (masses, "<f8"), (grades, "<f8")):
        digest.update(np.ascontiguousarray(arr, dtype=dtype).tobytes())
        digest.update(b"|")
    return digest.hexdigest()


class ExchangeRefused(Exception):
    """A refused exchange call: OPC UA status name, offending field, message."""

    def __init__(self, status: str, field: str, allowed: str, detail: str = ""):
        self.status = status
        self.field = field
        self.message = str(ValidationError(field, allowed, detail))
        super().__init__(self.message)


@dataclass
class InboundRecord:
    """A bin discharged onto the stockpile."""

    sequence: int
    tracking_id: int
    mass_kg: float
    grade: float
    hardness: float
    source: int
    time_s: float


class Belt:
    """Conveyor discretised in bins (structure of arrays over the slots)."""

    def __init__(self, length_m: float, bin_length_m: float, speed_m_s: float):
        self.bin_length_m = float(bin_length_m)
        self.n_bins = max(int(round(length_m / bin_length_m)), 1)
        self.speed_m_s = float(speed_m_s)
        self.offset_m = 0.0
        self.tracking_id = np.zeros(self.n_bins, dtype=np.uint64)
        self.mass = np.zeros(self.n_bins)
        self.grade = np.zeros(self.n_bins)
        self.hardness = np.zeros(self.n_bins)
        self.source = np.full(self.n_bins, -1, dtype=np.int32)
        self.shifts_done = 0
        """Shifts since the plant started: a bin put on slot 0 after shift ``s``
        is at slot ``shifts_done - s`` (how the ledger stores a belt's bins as
        rows written once, not the whole belt at every save)."""

    def state(self) -> dict:
        """The belt's motion as plain JSON data; its bins are restored from rows
        (``restore``)."""
        return {"offset_m": self.offset_m, "speed_m_s": self.speed_m_s,
                "n_bins": self.n_bins, "shifts_done": self.shifts_done}

    def restore(self, state: dict, loads=()) -> None:
        """Back to ``state()``; ``loads``: ``(shift, tracking_id, mass, grade,
        hardness, source)`` of the bins put on slot 0 after shift ``shift``
        (those already past the end are ignored)."""
        if int(state["n_bins"]) != self.n_bins:
            raise ValidationError("ledger", f"a belt of {self.n_bins} bins (the configuration's)",
                                  f"the stored belt has {state['n_bins']}")
        self.offset_m, self.speed_m_s = float(state["offset_m"]), float(state["speed_m_s"])
        self.shifts_done = int(state["shifts_done"])
        self.tracking_id[:], self.mass[:], self.grade[:], self.hardness[:] = 0, 0.0, 0.0, 0.0
        self.source[:] = -1
        for shift, tid, mass, grade, hardness, source in loads:
            slot = self.shifts_done - int(shift)
            if 0 <= slot < self.n_bins:
                self.tracking_id[slot], self.mass[slot], self.grade[slot] = tid, mass, grade
                self.hardness[slot], self.source[slot] = hardness, source

    def positions(self) -> np.ndarray:
        """Centre of each bin [m] from the loading point."""
        return (np.arange(self.n_bins) + 0.5) * self.bin_length_m + self.offset_m

    def shifts(self, dt: float) -> int:
        """Advance ``dt`` [s]; number of whole bin shifts that happen."""
        self.offset_m += self.speed_m_s * dt
        count = int(self.offset_m // self.bin_length_m)
        self.offset_m -= count * self.bin_length_m
        return count

    def shift(self) -> dict:
        """Move every bin one slot on; return the bin that left the head."""
        head = {"tracking_id": int(self.tracking_id[-1]), "mass": float(self.mass[-1]),
                "grade": float(self.grade[-1]), "hardness": float(self.hardness[-1]),
                "source": int(self.source[-1])}
        for arr, empty in ((self.tracking_id, 0), (self.mass, 0.0), (self.grade, 0.0),
                           (self.hardness, 0.0), (self.source, -1)):
            arr[1:] = arr[:-1].copy()
            arr[0] = empty
        self.shifts_done += 1
        return head


class PlantProcess:
    """CV101, SP201's exchange ledger and CV301 (no OPC UA in here).

    Parameters
    ----------
    config : dict
        A validated configuration (``opcua_server.config.load_config``).
    """

    def __init__(self, config: dict):
        self.config = config
        c1, c3, sp = config["cv101"], config["cv301"], config["sp201"]
        self.cv101 = Belt(c1["length_m"], c1["bin_length_m"], c1["belt_speed_m_s"])
        self.cv301 = Belt(c3["length_m"], c3["bin_length_m"], c3["belt_speed_m_s"])
        self.max_belt_speed = {"cv101": float(c1["max_belt_speed_m_s"]),
                               "cv301": float(c3["max_belt_speed_m_s"])}
        self.max_discharge_rate = float(sp["max_discharge_rate_kg_s"])
        # the configured setpoint takes effect at discharge_start_s (the pile fills before)
        self._scheduled_rate = float(sp["discharge_rate_kg_s"])
        self._discharge_start = float(sp.get("discharge_start_s", 0.0))
        self.discharge_rate_setpoint = self._scheduled_rate if self._discharge_start <= 0 else 0.0
        # (plant time it took effect [s], setpoint [kg/s]): a client that lags
        # behind the plant applies each setpoint from its own time, not late
        self.setpoint_changes: list[tuple[float, float]] = [(0.0, self.discharge_rate_setpoint)]
        self.lots = config["feed"]["lots"]
        self._lot_ends = np.cumsum([float(lot["duration_s"]) for lot in self.lots])
        self._initial_inventory_kg = float(sp.get("initial_inventory_kg", 0.0))
        self._initial_lot_kg = float(sp.get("initial_lot_kg", 15000.0))
        self.next_tracking_id = int(config["feed"]["first_tracking_id"])
        self.time = 0.0
        # inbound ledger
        self.last_sequence = 0
        self.acknowledged_sequence = 0
        self.pending: list[InboundRecord] = []
        self.entered_mass: dict[int, float] = {}
        self.source_of: dict[int, int] = {}
        # outbound ledger
        self.outbound_sequence = 0
        self.left_mass: dict[int, float] = {}
        self._grades: dict[int, float] = {}
        self.duplicate_reports = 0
        self.report_digests: dict[int, str] = {}
        self.loading_contents: dict[int, float] = {}
        self.cv301_contents: list[dict[int, float]] = [dict() for _ in range(self.cv301.n_bins)]
        self.cv301_contents[0] = self.loading_contents
        self.bins_out = 0
        self.delivered_mass_kg = 0.0
        self.delivered_by_source: dict[int, float] = {}
        self.outflow_log: list[dict] = []
        # what changed since the ledger store last saved (``opcua_server.ledger_store``):
        # ("inbound", InboundRecord), ("cv101_load", shift, tid, kg, grade, hardness,
        # source) and ("report", sequence, digest, log row, [(tid, left kg, grade)],
        # CV301 shift, [(tid, kg, grade)] loaded); ``revision`` counts every change but
        # the clock's
        self.journal: list[tuple] = []
        self.revision = 0
        # (plant time [s], mass [kg]) discharged onto SP201 / loaded onto CV301 in the
        # last FLOW_WINDOW_S: the belt scales' flow rates (not persisted: a restarted
        # server's flows start from its restart)
        self._cv101_flow: deque[tuple[float, float]] = deque()
        self._cv301_flow: deque[tuple[float, float]] = deque()

    # -------------------------------------------------------------- feeding
    def _lot_at(self, t: float) -> dict:
        period = self._lot_ends[-1]
        k = int(np.searchsorted(self._lot_ends, t % period, side="right"))
        return self.lots[min(k, len(self.lots) - 1)]

    def _load_cv101(self, t: float) -> None:
        belt = self.cv101
        if belt.speed_m_s <= 0:
            return
        lot = self._lot_at(t)
        belt.tracking_id[0] = self.next_tracking_id
        belt.mass[0] = float(lot["feed_rate_kg_s"]) * belt.bin_length_m / belt.speed_m_s
        belt.grade[0] = float(lot["grade"])
        belt.hardness[0] = float(lot["hardness"])
        belt.source[0] = int(lot["source"])
        self.journal.append(("cv101_load", belt.shifts_done, self.next_tracking_id,
                             float(belt.mass[0]), float(belt.grade[0]),
                             float(belt.hardness[0]), int(belt.source[0])))
        self.next_tracking_id += 1

    def _initial_inventory(self) -> list[InboundRecord]:
        """What SP201 holds when the plant starts (``sp201.initial_inventory_kg``): earlier
        production, in records of CV101's bin mass at t = 0, through the same loss-free
        exchange as every bin, so the audit accounts for it. It comes in lots of
        ``sp201.initial_lot_kg`` taken from the feed schedule's lots in turn (their
        grades, hardness and sources), so a pile starts with layers a plot can tell
        apart. A restored ledger already has it."""
        total = self._initial_inventory_kg
        self._initial_inventory_kg = 0.0
        if total <= 0 or self.last_sequence > 0 or self.time > 0:
            return []
        belt = self.cv101
        lot0 = self.lots[0]
        bin_kg = float(lot0["feed_rate_kg_s"]) * belt.bin_length_m / max(belt.speed_m_s, 1e-9)
        count = int(np.ceil(total / bin_kg))
        bins_per_lot = max(int(round(self._initial_lot_kg / bin_kg)), 1)
        records = []
        for k in range(count):
            lot = self.lots[(k // bins_per_lot) % len(self.lots)]
            mass = min(bin_kg, total - k * bin_kg)
            head = {"tracking_id": self.next_tracking_id, "mass": mass,
                    "grade": float(lot["grade"]), "hardness": float(lot["hardness"]),
                    "source": int(lot["source"])}
            self.next_tracking_id += 1
            records.append(self._discharge(head, 0.0))
        self.revision += 1
        return records

    # --------------------------------------------------------------- advance
    def advance(self, dt: float) -> list[InboundRecord]:
        """Advance the plant ``dt`` [s]; return the new inbound records (at the first
        call of a new plant, with its initial inventory first)."""
        dt = float(dt)
        if not np.isfinite(dt) or dt < 0:
            raise ValidationError("dt", "finite and >= 0 s", f"got {dt!r}")
        new = self._initial_inventory() if self._initial_inventory_kg > 0 else []
        belt = self.cv101
        offset = belt.offset_m
        for k in range(belt.shifts(dt)):
            # the k-th shift happens when the belt has moved (k+1) bins from `offset`
            t_shift = self.time + ((k + 1) * belt.bin_length_m - offset) / belt.speed_m_s
            head = belt.shift()
            self._load_cv101(t_shift)
            if head["mass"] > 0:
                new.append(self._discharge(head, t_shift))
        shifts = self.cv301.shifts(dt)
        for _ in range(shifts):
            self._shift_cv301()
        if shifts or new or belt.offset_m < offset:
            self.revision += 1
        self.time += dt
        if 0 < self._discharge_start <= self.time:
            self.discharge_rate_setpoint = self._scheduled_rate
            self._record_setpoint(self._discharge_start)
            self._discharge_start = 0.0
        return new

    def _discharge(self, head: dict, t: float) -> InboundRecord:
        self.last_sequence += 1
        record = InboundRecord(self.last_sequence, head["tracking_id"], head["mass"],
                               head["grade"], head["hardness"], head["source"], t)
        self.pending.append(record)
        self.journal.append(("inbound", record))
        self._cv101_flow.append((t, record.mass_kg))
        self.entered_mass[record.tracking_id] = record.mass_kg
        self.source_of[record.tracking_id] = record.source
        return record

    def _shift_cv301(self) -> None:
        belt = self.cv301
        delivered = self.cv301_contents[-1]
        for tid, mass in delivered.items():
            source = self.source_of.get(tid, -1)
            self.delivered_by_source[source] = self.delivered_by_source.get(source, 0.0) + mass
            self.delivered_mass_kg += mass
        belt.shift()
        if self.loading_contents:
            self.bins_out += 1
        # slot 0 is always the loading bin: the loaded one moves on to slot 1
        # (before, it stayed in slot 0 as well and, without an outflow report
        # before the next shift, was carried, and delivered, twice)
        self.loading_contents = {}
        self.cv301_contents = [self.loading_contents] + self.cv301_contents[:-1]
        self._refresh_cv301_slot(0)

    def _refresh_cv301_slot(self, slot: int) -> None:
        contents = self.cv301_contents[slot]
        mass = sum(contents.values())
        self.cv301.mass[slot] = mass
        self.cv301.tracking_id[slot] = next(iter(contents), 0)
        self.cv301.grade[slot] = (sum(m * self._grades.get(t, 0.0) for t, m in contents.items())
                                  / mass if mass > 0 else 0.0)

    # -------------------------------------------------------------- inbound
    def acknowledge(self, sequence: int) -> int:
        """Drop pending records up to ``sequence``; return the acknowledged number."""
        sequence = int(sequence)
        if sequence < 0 or sequence > self.last_sequence:
            raise ExchangeRefused("BadOutOfRange", "sequence",
                                  f"in [0, {self.last_sequence}] (the last record sent)",
                                  f"got {sequence}")
        if sequence > self.acknowledged_sequence:
            self.acknowledged_sequence = sequence
            self.revision += 1
            self.pending = [r for r in self.pending if r.sequence > sequence]
        return self.acknowledged_sequence

    def pending_arrays(self) -> dict[str, np.ndarray]:
        """The unacknowledged records as plain arrays (the readable pending list)."""
        p = self.pending
        return {
            "sequence": np.array([r.sequence for r in p], dtype=np.uint64),
            "tracking_id": np.array([r.tracking_id for r in p], dtype=np.uint64),
            "mass": np.array([r.mass_kg for r in p], dtype=np.float64),
            "grade": np.array([r.grade for r in p], dtype=np.float64),
            "hardness": np.array([r.hardness for r in p], dtype=np.float64),
            "source": np.array([r.source for r in p], dtype=np.int32),
            "time": np.array([r.time_s for r in p], dtype=np.float64),
        }

    # ------------------------------------------------------------- outbound
    def report_outflow(self, sequence: int, tracking_ids, masses, grades) -> str:
        """Apply one outflow report once; return "applied" or "already applied".

        Refused (``ExchangeRefused``, nothing changed): sequence 0, a gap
        in the sequence, an applied number with other contents (a replay
        that is a conflict), more than ``MAX_REPORT_ROWS`` tracking ids, arrays of different lengths, a repeated tracking id,
        masses not finite and > 0, grades outside [0, 1], a tracking id that
        never entered the stockpile, or more mass of a tracking id than
        entered.
        """
        sequence = int(sequence)
        tids = np.asarray(tracking_ids, dtype=np.uint64).ravel()
        mass = np.asarray(masses, dtype=np.float64).ravel()
        grade = np.asarray(grades, dtype=np.float64).ravel()
        if tids.size > MAX_REPORT_ROWS:
            raise ExchangeRefused("BadTooManyOperations", "tracking_ids",
                                  f"at most {MAX_REPORT_ROWS} per report", f"got {tids.size}")
        if sequence < 1:
            raise ExchangeRefused("BadSequenceNumberInvalid", "sequence", ">= 1", "got 0")
        digest = report_digest(tids, mass, grade)
        if sequence <= self.outbound_sequence:
            if self.report_digests.get(sequence) != digest:
                raise ExchangeRefused("BadSequenceNumberInvalid", "sequence",
                                      "a new number for a new report",
                                      f"report {sequence} was applied with other contents")
            self.duplicate_reports += 1
            return "already applied"
        if sequence != self.outbound_sequence + 1:
            raise ExchangeRefused("BadSequenceNumberInvalid", "sequence",
                                  f"{self.outbound_sequence + 1} (the next outflow number)",
                                  f"got {sequence}")
        for name, arr in (("masses", mass), ("grades", grade)):
            if arr.size != tids.size:
                raise ExchangeRefused("BadInvalidArgument", name,
                                      "one value per tracking id",
                                      f"got {arr.size} for {tids.size} tracking ids")
        if np.unique(tids).size != tids.size:
            raise ExchangeRefused("BadInvalidArgument", "tracking_ids",
                                  "distinct within one report", "a tracking id is repeated")
        bad = ~np.isfinite(mass) | (mass <= 0)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ExchangeRefused("BadOutOfRange", "masses", "finite and > 0 kg",
                                  f"got {float(mass[k])} at index {k}")
        bad = ~np.isfinite(grade) | (grade < 0) | (grade > 1)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ExchangeRefused("BadOutOfRange", "grades", "in [0, 1]",
                                  f"got {float(grade[k])} at index {k}")
        for k, tid in enumerate(tids.tolist()):
            entered = self.entered_mass.get(tid)
            if entered is None:
                raise ExchangeRefused("BadInvalidArgument", "tracking_ids",
                                      "ids of bins that entered the stockpile",
                                      f"tracking id {tid} at index {k} never entered")
            total = self.left_mass.get(tid, 0.0) + mass[k]
            if total > entered * (1 + MASS_TOLERANCE) + 1e-12:
                raise ExchangeRefused("BadOutOfRange", "masses",
                                      f"<= the {entered:.6g} kg of tracking id {tid} that entered",
                                      f"{total:.9g} kg would have left in total")
        # accepted: apply
        self.outbound_sequence = sequence
        self.report_digests[sequence] = digest
        for tid, m, g in zip(tids.tolist(), mass.tolist(), grade.tolist()):
            self.left_mass[tid] = self.left_mass.get(tid, 0.0) + m
            self.loading_contents[tid] = self.loading_contents.get(tid, 0.0) + m
            self._grades[tid] = g
        self.cv301_contents[0] = self.loading_contents
        self._refresh_cv301_slot(0)
        self.outflow_log.append({"time_s": self.time, "sequence": sequence,
                                 "mass_kg": float(mass.sum()),
                                 "by_source": self._by_source(tids, mass)})
        self._cv301_flow.append((self.time, float(mass.sum())))
        loaded = list(zip(tids.tolist(), mass.tolist(), grade.tolist()))
        self.journal.append(("report", sequence, digest, self.outflow_log[-1],
                             [(tid, self.left_mass[tid], self._grades[tid])
                              for tid in tids.tolist()], self.cv301.shifts_done, loaded))
        self.revision += 1
        return "applied"

    def _by_source(self, tids: np.ndarray, mass: np.ndarray) -> dict[str, float]:
        out: dict[str, float] = {}
        for tid, m in zip(tids.tolist(), mass.tolist()):
            key = str(self.source_of.get(tid, -1))
            out[key] = out.get(key, 0.0) + m
        return out

    # ------------------------------------------------------------- setpoints
    def set_discharge_rate(self, rate: float) -> None:
        """Stockpile feeder setpoint [kg/s] in [0, max_discharge_rate]."""
        rate = float(rate)
        if not np.isfinite(rate) or rate < 0 or rate > self.max_discharge_rate:
            raise ExchangeRefused("BadOutOfRange", "DischargeRateSetpoint",
                                  f"in [0, {self.max_discharge_rate:g}] kg/s", f"got {rate!r}")
        self.discharge_rate_setpoint = rate
        self._discharge_start = 0.0  # the operator's setpoint stands
        self._record_setpoint(self.time)
        self.revision += 1

    def _record_setpoint(self, effective_s: float) -> None:
        changes = self.setpoint_changes
        changes.append((float(effective_s), self.discharge_rate_setpoint))
        del changes[:-SETPOINT_CHANGES_KEPT]

    def set_belt_speed(self, belt: str, speed: float) -> None:
        """Belt speed [m/s] of ``cv101`` or ``cv301`` in [0, max]."""
        speed = float(speed)
        top = self.max_belt_speed[belt]
        if not np.isfinite(speed) or speed < 0 or speed > top:
            raise ExchangeRefused("BadOutOfRange", f"{belt.upper()}.BeltSpeed",
                                  f"in [0, {top:g}] m/s", f"got {speed!r}")
        getattr(self, belt).speed_m_s = speed
        self.revision += 1

    @property
    def mass_in_kg(self) -> float:
        """Total mass discharged onto SP201 [kg]."""
        return float(sum(self.entered_mass.values()))

    @property
    def mass_out_kg(self) -> float:
        """Total mass reported out of SP201 onto CV301 [kg]."""
        return float(sum(self.left_mass.values()))

    def mass_flow(self, belt: str) -> float:
        """Mass flow [kg/s] over the last ``FLOW_WINDOW_S`` of plant time: discharged
        from CV101 onto SP201 (``"cv101"``) or loaded onto CV301 (``"cv301"``)."""
        flow = self._cv101_flow if belt == "cv101" else self._cv301_flow
        while flow and flow[0][0] <= self.time - FLOW_WINDOW_S:
            flow.popleft()
        window = min(FLOW_WINDOW_S, self.time)
        return sum(m for _, m in flow) / window if window > 0 else 0.0

    # ----------------------------------------------------------- persistence
    def state(self) -> dict:
        """Everything but the per-tracking-id and per-record tables and the bins
        on the belts, as JSON data of a size that does not grow with the belts
        (the ledger store keeps those as rows written once, from ``journal``)."""
        return {
            "time": self.time, "next_tracking_id": self.next_tracking_id,
            "last_sequence": self.last_sequence, "acknowledged_sequence": self.acknowledged_sequence,
            "outbound_sequence": self.outbound_sequence, "duplicate_reports": self.duplicate_reports,
            "discharge_rate_setpoint": self.discharge_rate_setpoint,
            "discharge_start": self._discharge_start,
            "setpoint_changes": [list(c) for c in self.setpoint_changes],
            "cv101": self.cv101.state(), "cv301": self.cv301.state(),
            "bins_out": self.bins_out, "delivered_mass_kg": self.delivered_mass_kg,
            "delivered_by_source": list(self.delivered_by_source.items()),
        }

    def restore(self, state: dict, inbound: list[InboundRecord], bins: list[tuple],
                reports: list[tuple], cv101_loads=(), cv301_loads=()) -> None:
        """Back to a saved state: ``state()``'s dict, the inbound records not yet
        acknowledged, ``(tracking_id, entered kg, source, left kg, grade)`` per
        bin, ``(sequence, digest, log row)`` per applied outflow report, the
        bins loaded onto CV101 (``Belt.restore``'s rows) and the outflow loaded
        onto CV301, ``(shift, tracking_id, kg, grade)`` in the order reported
        (slot ``shifts_done - shift``: each slot's contents and grade as they
        were, summed in the same order)."""
        self.time = float(state["time"])
        self.next_tracking_id = int(state["next_tracking_id"])
        self.last_sequence = int(state["last_sequence"])
        self.acknowledged_sequence = int(state["acknowledged_sequence"])
        self.outbound_sequence = int(state["outbound_sequence"])
        self.duplicate_reports = int(state["duplicate_reports"])
        self.discharge_rate_setpoint = float(state["discharge_rate_setpoint"])
        self._discharge_start = float(state["discharge_start"])
        self.setpoint_changes = [tuple(c) for c in state["setpoint_changes"]]
        self.cv101.restore(state["cv101"], cv101_loads)
        self.cv301.restore(state["cv301"])
        belt = self.cv301
        self.cv301_contents = [dict() for _ in range(belt.n_bins)]
        slot_grades: list[dict[int, float]] = [dict() for _ in range(belt.n_bins)]
        for shift, tid, mass, grade in cv301_loads:
            slot = belt.shifts_done - int(shift)
            if 0 <= slot < belt.n_bins:
                contents = self.cv301_contents[slot]
                contents[tid] = contents.get(tid, 0.0) + mass
                slot_grades[slot][tid] = grade  # the latest report's, as when it moved on
        for slot, contents in enumerate(self.cv301_contents):
            mass = sum(contents.values())
            belt.mass[slot] = mass
            belt.tracking_id[slot] = next(iter(contents), 0)
            belt.grade[slot] = (sum(m * slot_grades[slot][t] for t, m in contents.items())
                                / mass if mass > 0 else 0.0)
        self.loading_contents = self.cv301_contents[0]
        self.bins_out = int(state["bins_out"])
        self.delivered_mass_kg = float(state["delivered_mass_kg"])
        self.delivered_by_source = {int(k): v for k, v in state["delivered_by_source"]}
        self.pending = sorted(inbound, key=lambda r: r.sequence)
        self.entered_mass = {tid: m for tid, m, _, _, _ in bins}
        self.source_of = {tid: src for tid, _, src, _, _ in bins}
        self.left_mass = {tid: left for tid, _, _, left, _ in bins if left > 0}
        self._grades = {tid: g for tid, _, _, left, g in bins if left > 0}
        self.report_digests = {seq: digest for seq, digest, _ in reports}
        self.outflow_log = [row for _, _, row in sorted(reports, key=lambda r: r[0])]
        self.journal = []

    # ---------------------------------------------------------------- ledger
    def ledger(self) -> dict:
        """Everything needed to audit the exchange (written at shutdown)."""
        return {
            "time_s": self.time,
            "bins_in": self.last_sequence,
            "inbound_acknowledged": self.acknowledged_sequence,
            "pending": len(self.pending),
            "outbound_sequence": self.outbound_sequence,
            "duplicate_reports_ignored": self.duplicate_reports,
            "bins_out": self.bins_out + (1 if self.loading_contents else 0),
            "mass_in_kg": self.mass_in_kg, "mass_out_kg": self.mass_out_kg,
            "delivered_mass_kg": self.delivered_mass_kg,
            "delivered_by_source": {str(k): v for k, v in self.delivered_by_source.items()},
            "entered": {str(k): v for k, v in self.entered_mass.items()},
            "left": {str(k): v for k, v in self.left_mass.items()},
            "source_of": {str(k): v for k, v in self.source_of.items()},
            "outflow_log": self.outflow_log,
        }
