"""Durable ledger of the mock 800xA server: SQLite in WAL mode, one file per plant.

A server stopped with SIGTERM or killed with SIGKILL comes back with the same
clock, belts, inbound sequence, pending bins, outbound sequence, applied
reports and tracking ids, so a restart loses and duplicates nothing and never
gives a tracking id twice. Every change is committed (``synchronous=FULL``)
*before* the server answers the call or emits the event that makes it
visible: what a client has seen, the ledger has.

File ``STATE/ledger.sqlite``:

* ``meta(key, value)``: ``ledger_id`` (a UUID made with the file; the client
  keeps it in its checkpoint and refuses a server with another ledger),
  ``schema`` (``SCHEMA_VERSION``) and ``state`` (``PlantProcess.state()`` as
  JSON: clock, counters, the belts' motion and shift counts, setpoints; a few
  hundred bytes whatever the belts hold);
* ``inbound(sequence, tracking_id, mass_kg, grade, hardness, source, time_s)``:
  every discharged bin; the pending ones are those above the acknowledged
  sequence;
* ``bins(tracking_id, entered_kg, source, left_kg, grade)``: per tracking id;
* ``reports(sequence, digest, log)``: applied outflow reports (the digest
  tells a resend from a conflicting replay);
* ``cv101_loads(shift, tracking_id, mass_kg, grade, hardness, source)``: the
  bin put on CV101's loading slot after its shift number ``shift``;
* ``cv301_loads(row, shift, tracking_id, mass_kg, grade)``: the outflow loaded
  onto CV301 while its shift count was ``shift``, in the order reported.

A save writes only what changed: new rows, and the small ``state``. The
belts' rows are written once, when a bin is put on the belt, and deleted
once it has left (it is then in ``inbound`` or delivered): before, the
whole belts were encoded to JSON at every save (6 % of the server's
py-spy samples at 1,000 bins/s with 2,000-bin belts).
"""

from __future__ import annotations

import asyncio
import json
import sqlite3
import time
import uuid
from pathlib import Path

from cosim.errors import ValidationError
from opcua_server.process import InboundRecord, PlantProcess

SCHEMA_VERSION = 2
SAVE_CLOCK_EVERY_S = 1.0
"""Wall seconds [s] between saves when only the clock moved (anything else
is saved at once)."""

_TABLES = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS inbound (sequence INTEGER PRIMARY KEY, tracking_id TEXT NOT NULL,
    mass_kg REAL NOT NULL, grade REAL NOT NULL, hardness REAL NOT NULL, source INTEGER NOT NULL,
    time_s REAL NOT NULL);
CREATE TABLE IF NOT EXISTS bins (tracking_id TEXT PRIMARY KEY, entered_kg REAL NOT NULL,
    source INTEGER NOT NULL, left_kg REAL NOT NULL DEFAULT 0, grade REAL NOT NULL DEFAULT 0);
CREATE TABLE IF NOT EXISTS reports (sequence INTEGER PRIMARY KEY, digest TEXT NOT NULL,
    log TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS cv101_loads (shift INTEGER PRIMARY KEY, tracking_id TEXT NOT NULL,
    mass_kg REAL NOT NULL, grade REAL NOT NULL, hardness REAL NOT NULL, source INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS cv301_loads (row INTEGER PRIMARY KEY, shift INTEGER NOT NULL,
    tracking_id TEXT NOT NULL, mass_kg REAL NOT NULL, grade REAL NOT NULL);
CREATE INDEX IF NOT EXISTS cv301_loads_shift ON cv301_loads (shift);
"""
# tracking ids are uint64: stored as decimal text (SQLite integers are signed 64-bit)


class LedgerStore:
    """The ledger file of one plant; ``load`` into a process, ``save`` its changes."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            # the default isolation level: ``with self.db`` is one transaction, one fsync
            # used by one thread at a time: ``save_async`` writes from a worker thread
            self.db = sqlite3.connect(self.path, timeout=10.0, check_same_thread=False)
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=FULL")
            self.db.executescript(_TABLES)
            meta = dict(self.db.execute("SELECT key, value FROM meta"))
        except sqlite3.DatabaseError as exc:
            raise ValidationError("ledger", "an SQLite ledger file of serve-800xa",
                                  f"{self.path}: {exc}") from None
        if meta.get("schema", str(SCHEMA_VERSION)) != str(SCHEMA_VERSION):
            raise ValidationError("ledger", f"schema {SCHEMA_VERSION}",
                                  f"{self.path} has schema {meta['schema']}")
        self.ledger_id = meta.get("ledger_id")
        self.fresh = self.ledger_id is None
        if self.fresh:
            self.ledger_id = str(uuid.uuid4())
            with self.db:
                self.db.executemany("INSERT INTO meta VALUES (?, ?)",
                                    [("ledger_id", self.ledger_id),
                                     ("schema", str(SCHEMA_VERSION))])
        self._saved_revision = None
        self._saved_at = -float("inf")
        self._writing = asyncio.Lock()

    def load(self, process: PlantProcess) -> bool:
        """Restore ``process`` from the file; False if the file had no state yet."""
        row = self.db.execute("SELECT value FROM meta WHERE key = 'state'").fetchone()
        if row is None:
            return False
        state = json.loads(row[0])
        acked = int(state["acknowledged_sequence"])
        inbound = [InboundRecord(seq, int(tid), m, g, h, src, t) for seq, tid, m, g, h, src, t in
                   self.db.execute("SELECT * FROM inbound WHERE sequence > ?", (acked,))]
        bins = [(int(tid), m, src, left, g) for tid, m, src, left, g in
                self.db.execute("SELECT * FROM bins")]
        reports = [(seq, digest, json.loads(log)) for seq, digest, log in
                   self.db.execute("SELECT * FROM reports")]
        cv101 = [(shift, int(tid), m, g, h, src) for shift, tid, m, g, h, src in
                 self.db.execute("SELECT * FROM cv101_loads")]
        cv301 = [(shift, int(tid), m, g) for shift, tid, m, g in
                 self.db.execute("SELECT shift, tracking_id, mass_kg, grade FROM cv301_loads "
                                 "ORDER BY row")]
        process.restore(state, inbound, bins, reports, cv101, cv301)
        self._saved_revision = process.revision
        return True

    def save(self, process: PlantProcess, force: bool = False) -> None:
        """Commit what changed since the last save (the journal and the state).

        Only the clock moved: saved at most every ``SAVE_CLOCK_EVERY_S``
        (restarting from a slightly earlier time is consistent: belts and
        counters are those of that time), unless ``force``.
        """
        batch = self._take(process, force)
        if batch is not None:
            self._write(*batch)

    async def save_async(self, process: PlantProcess, force: bool = False) -> None:
        """``save``, with the commit (its fsync: 5 ms at the median on this
        machine, 16 ms at p99, some 40 a second at 1,000 bins/s) in a worker
        thread, so the server's event loop serves other requests meanwhile. What
        changed is taken at once, in the caller's thread; saves are written in
        the order they were taken. The caller makes nothing visible before this
        returns."""
        async with self._writing:  # FIFO: the batches reach the file in order
            batch = self._take(process, force)
            if batch is not None:
                await asyncio.to_thread(self._write, *batch)

    def _take(self, process: PlantProcess, force: bool) -> tuple | None:
        """What a save writes, taken from ``process`` now: (journal, state JSON,
        the first shift still on each belt); None if nothing is due."""
        now = time.monotonic()
        if not (force or process.journal or process.revision != self._saved_revision
                or now - self._saved_at >= SAVE_CLOCK_EVERY_S):
            return None
        journal, process.journal = process.journal, []
        self._saved_revision = process.revision
        self._saved_at = now
        state = json.dumps(process.state(), allow_nan=False)
        on_belts = tuple(belt.shifts_done - belt.n_bins for belt in (process.cv101, process.cv301))
        return journal, state, on_belts

    def _write(self, journal: list, state: str, on_belts: tuple) -> None:
        db = self.db
        with db:  # one transaction
            # consecutive entries of one kind in one executemany, in journal order
            inbound, loads = [], []
            for entry in journal:
                kind = entry[0]
                if kind != "inbound" and inbound:
                    self._insert_inbound(inbound)
                    inbound = []
                if kind != "cv101_load" and loads:
                    db.executemany("INSERT INTO cv101_loads VALUES (?, ?, ?, ?, ?, ?)", loads)
                    loads = []
                if kind == "inbound":
                    inbound.append(entry[1])
                elif kind == "cv101_load":
                    shift, tid, mass, grade, hardness, source = entry[1:]
                    loads.append((shift, str(tid), mass, grade, hardness, source))
                else:
                    _, sequence, digest, log, rows, shift, loaded = entry
                    db.execute("INSERT INTO reports VALUES (?, ?, ?)",
                               (sequence, digest, json.dumps(log, allow_nan=False)))
                    db.executemany("UPDATE bins SET left_kg = ?, grade = ? WHERE tracking_id = ?",
                                   [(left, grade, str(tid)) for tid, left, grade in rows])
                    db.executemany("INSERT INTO cv301_loads (shift, tracking_id, mass_kg, grade) "
                                   "VALUES (?, ?, ?, ?)",
                                   [(shift, str(tid), m, g) for tid, m, g in loaded])
            if inbound:
                self._insert_inbound(inbound)
            if loads:
                db.executemany("INSERT INTO cv101_loads VALUES (?, ?, ?, ?, ?, ?)", loads)
            # the bins that have left a belt: in ``inbound`` (CV101) or delivered (CV301)
            for table, gone in zip(("cv101_loads", "cv301_loads"), on_belts):
                db.execute(f"DELETE FROM {table} WHERE shift <= ?", (gone,))
            db.execute("INSERT OR REPLACE INTO meta VALUES ('state', ?)", (state,))

    def _insert_inbound(self, records: list[InboundRecord]) -> None:
        self.db.executemany("INSERT INTO inbound VALUES (?, ?, ?, ?, ?, ?, ?)",
                            [(r.sequence, str(r.tracking_id), r.mass_kg, r.grade, r.hardness,
                              r.source, r.time_s) for r in records])
        self.db.executemany("INSERT OR REPLACE INTO bins (tracking_id, entered_kg, source) "
                            "VALUES (?, ?, ?)",
                            [(str(r.tracking_id), r.mass_kg, r.source) for r in records])

    def close(self) -> None:
        self.db.close()
