"""The stockpile surrogate as an OPC UA client of the (mock) 800xA plant.

Source: paper section "Integration test" (exchange of bins at the discharge
point, the discharge-rate control signal, and macro-tracking messages for the
outgoing conveyor). The exchange loses nothing.

One *exchange cycle* (every ``cycle_s`` wall seconds, or one
``Plant.AdvanceTime(period_s)`` call in lockstep):

1. one Read: SimulationTime, the discharge-rate setpoint, the inbound
   sequence numbers, the setpoint changes and the records of the pending
   list the client has not seen yet (an IndexRange from the first unseen
   one; the whole list after a reconnect, or if the server ignores the
   range);
2. step the asset up to the server's time in sub-steps of at most ``dt_s``,
   applying inbound records in sequence order at their discharge times
   (never past a record known to exist but not read yet); a FIFO pile in
   slices of at most ``slice_s``, each slice's records received together
   and one step over it where that is exact (``advance_to``); at most
   ``cycle_budget_s`` of wall time, the rest in the next cycles; the outflow
   of the cycle becomes one outbound report with the next outbound sequence
   number, put in the *outbox*;
3. write the checkpoint (asset, last applied inbound number, outbox)
   atomically: every cycle in lockstep, else at most every
   ``checkpoint_every_s`` of wall time (a checkpoint costs a file write and
   an fsync; between two, reports wait in the outbox and records
   unacknowledged on the server);
4. after a checkpoint, one Call request sends the outbox (``ReportOutflow``
   per report, in order; a repeat is answered "already applied" and dropped)
   and acknowledges the last applied inbound number; pipelined with it, one
   Write of HeldMass, AverageGrade, Heartbeat and SurrogateTime and one Read
   of SimulationTime (the lag).

No event subscription: the records come from the pending list, read in the
same request as the clock, so the client never steps past a record the
server had discharged by the time it read (decoding one event per bin cost
more than the stepping at 100 bins/s, profiled).

Exactly once: an inbound record is acknowledged only after a checkpoint that
contains its effect, and an outbound report is sent only after a checkpoint
that contains it. After a crash the client restarts from the checkpoint:
records applied after it are still pending on the server and are applied
again from the restored state (once), and reports sent after it are
answered "already applied". After a lost connection the client reconnects
and resynchronises from the pending list.
"""

from __future__ import annotations

import asyncio
import bisect
import json
import logging
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cosim.errors import ValidationError
from surrogate.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from surrogate.stockpile import StockpileAsset

log = logging.getLogger("surrogate.client")

CHECKPOINT_VERSION = 2
WARM_UP_BINS = 10
"""Bins of 500 kg the throw-away asset of ``warm_up`` is fed, one per step."""
WARM_UP_S = 10.0
"""Plant time [s] ``warm_up`` runs its throw-away asset: the bins' fall from the
inlet (about 3.5 s from 60 m), their landing and their joining the bulk."""

LAG_WARNING_S = 2.0
"""Lag [s of plant time] behind the server above which the client says on
stderr that it does not keep real time (at most every 10 s of wall time)."""


class LedgerChanged(Exception):
    """The server's ledger is not the one the stockpile's state was exchanged with."""


@dataclass
class ClientOptions:
    """Options of the stockpile client (times in seconds of simulation unless wall)."""

    server_url: str
    username: str = "surrogate"
    password: str = ""
    certificate: Path | None = None
    private_key: Path | None = None
    server_certificate: Path | None = None
    insecure: bool = False
    model: str = "fifo"
    storage_options: dict = field(default_factory=dict)
    source_names: dict = field(default_factory=dict)
    """Display name per source index (``StockpileAsset``'s ``source_names``)."""
    seed: int = 0
    particle_mass_kg: float = 100.0
    dt_s: float = 0.5
    cycle_s: float = 0.1
    lockstep: bool = False
    period_s: float = 1.0
    duration_s: float | None = None
    checkpoint: Path | None = None
    summary: Path | None = None
    node_map: Path | None = None
    rest_port: int | None = None
    rest_port_file: Path | None = None
    cycle_budget_s: float = 0.25
    """Wall time [s] one exchange cycle may spend stepping (not in lockstep): a
    client far behind catches up in cycles of at most this, so its session
    stays alive and a stop (SIGTERM) is taken within about this."""
    slice_s: float = 5.0
    """Longest step [s of plant time] of a storage model whose arrivals join the
    tail (FIFO), which is stepped one slice at a time (``advance_to``)."""
    checkpoint_every_s: float = 0.5
    """Least wall time [s] between two checkpoints (and so between two sends of
    the outbox and acknowledgements) outside lockstep."""
    reconnect_s: float = 1.0
    timeout_s: float = 4.0


@dataclass
class ClientState:
    """Everything the checkpoint holds."""

    asset: StockpileAsset
    last_applied: int = 0
    outflow_sequence: int = 0
    outbox: list = field(default_factory=list)
    heartbeat: int = 0
    ledger_id: str | None = None  # the server ledger this state was exchanged with
    version: int = CHECKPOINT_VERSION


class StockpileClient:
    """Runs the stockpile asset against the plant server (see module docstring)."""

    def __init__(self, options: ClientOptions):
        self.o = options
        self.state = self._restore() or ClientState(
            StockpileAsset(options.model, seed=options.seed,
                           particle_mass_kg=options.particle_mass_kg,
                           storage_options=options.storage_options,
                           source_names=options.source_names))
        if options.source_names:  # the names given now, also over a checkpoint's
            self.state.asset.source_names = {int(k): str(v)
                                             for k, v in options.source_names.items()}
        self.inbox: dict[int, dict] = {}
        self.known_sequence = self.state.last_applied
        self.need_sync = True
        self.acked = -1
        self.server_acked = -1  # the server's acknowledged sequence, as last read
        self.server_last_sequence = 0  # the last inbound number the server had given
        self._checkpointed_at = -math.inf
        self._send_now = False  # this cycle wrote a checkpoint: send and acknowledge
        self.step_times_ms: list[float] = []
        self.largest_step_s = 0.0  # the longest single asset step [s of plant time]
        self.max_lag_s = 0.0
        self.lags_s: list[float] = []
        self.reconnects = 0
        self._stop = asyncio.Event()
        self.exchange_idle = asyncio.Event()
        """Set except while an exchange cycle runs: the REST interface answers in
        between (``surrogate.rest.create_app``), so that reading the pile never
        stretches a cycle (its lag)."""
        self.exchange_idle.set()
        self.nodes: dict = {}
        # [(plant time [s], setpoint [kg/s])] the plant published, oldest first;
        # empty: the setpoint read in the cycle applies to the whole cycle
        self.setpoint_changes: list[tuple[float, float]] = []
        self._lag_warned_at = -math.inf
        self._cycle_budget_s = None  # wall-time budget of the running cycle's stepping
        self.server_instance = None

    @property
    def asset(self) -> StockpileAsset:
        return self.state.asset

    # ----------------------------------------------------------- checkpoint
    def _restore(self) -> ClientState | None:
        path = self.o.checkpoint
        if path is None or not Path(path).exists():
            return None
        state = load_checkpoint(path)  # data only: reading it runs no code from the file
        if not isinstance(state, ClientState) or state.version != CHECKPOINT_VERSION:
            raise CheckpointError(path, f"not a version {CHECKPOINT_VERSION} stockpile state")
        if state.asset.model_name != self.o.model:
            raise ValidationError("model", f"{state.asset.model_name!r} (the checkpoint's model)",
                                  f"got {self.o.model!r}")
        print(f"stockpile: resumed from {path} at t={state.asset.time:.3f} s, "
              f"last applied inbound {state.last_applied}, {len(state.outbox)} report(s) unsent",
              file=sys.stderr, flush=True)
        return state

    def _checkpoint(self) -> None:
        if self.o.checkpoint is not None:
            save_checkpoint(self.o.checkpoint, self.state)

    # ------------------------------------------------------------ exchange
    def _accept_records(self, records: list[dict]) -> None:
        for r in records:
            seq = r["sequence"]
            if seq > self.state.last_applied:
                self.inbox.setdefault(seq, r)
            self.known_sequence = max(self.known_sequence, seq)

    def advance_to(self, target_time: float, budget_s: float | None = None) -> dict | None:
        """Step the asset to ``target_time`` applying inbound records in order;
        return this cycle's outflow report (or None).

        ``budget_s`` [wall s] (default: the running cycle's, ``cycle_budget_s``
        outside lockstep): stop stepping (short of ``target_time``) once this
        much wall time is spent, so a client far behind catches up over several
        cycles and keeps its session alive (the next cycle goes on).

        A storage model whose arrivals join the tail (FIFO,
        ``arrivals_join_the_tail``) is stepped in slices of at most ``slice_s``
        of plant time, each slice's records received together and one step
        over it, wherever that is exact (the feeder's credit over the slice
        below the mass held at its start, see ``cosim.storage``); elsewhere,
        and for every other model, in sub-steps of at most ``dt_s`` to each
        record's discharge time in turn.
        """
        started = time.perf_counter()
        budget_s = budget_s if budget_s is not None else self._cycle_budget_s
        deadline = started + budget_s if budget_s is not None else math.inf
        outflow: dict[int, list[float]] = {}
        asset = self.asset

        def step_to(t_end: float) -> bool:
            """Step to ``t_end``; False if the wall-time budget ran out first."""
            while asset.time < t_end - 1e-12:
                if time.perf_counter() > deadline:
                    return False
                next_change = self._setpoint_in_force()
                self._step(min(self.o.dt_s, t_end - asset.time, next_change - asset.time),
                           outflow)
            return True

        if not asset.started:
            self._receive_initial_inventory()
        batch = asset.storage.arrivals_join_the_tail
        in_time = True
        while True:
            if batch and self._slice(target_time, deadline, outflow):
                continue
            nxt = self.inbox.get(self.state.last_applied + 1)
            if nxt is None:
                if self.server_last_sequence > self.state.last_applied:
                    # the record exists on the server but was not read: its discharge
                    # time is unknown, so stepping on could step past it
                    self.need_sync = True  # read the whole pending list next cycle
                    in_time = False
                break
            if nxt["time"] > target_time:
                break
            if not (in_time := step_to(nxt["time"])):
                break
            asset.receive_bin(nxt["tracking_id"], nxt["mass"], nxt["grade"], nxt["hardness"],
                              nxt["source"])
            del self.inbox[nxt["sequence"]]
            self.state.last_applied = nxt["sequence"]
        if in_time:
            step_to(target_time)
        self.step_times_ms.append((time.perf_counter() - started) * 1e3)
        if not outflow:
            return None
        self.state.outflow_sequence += 1
        tids = sorted(outflow)
        masses = [outflow[t][0] for t in tids]
        grades = [min(max(outflow[t][1] / outflow[t][0], 0.0), 1.0) for t in tids]
        report = {"sequence": self.state.outflow_sequence, "tracking_ids": tids,
                  "masses": masses, "grades": grades}
        self.state.outbox.append(report)
        return report

    def _setpoint_in_force(self) -> float:
        """Set the feeder to the setpoint in force at the asset's plant time;
        return the plant time of the next change (inf if none is known)."""
        changes, now = self.setpoint_changes, self.asset.time
        if not changes:  # the setpoint read in the cycle applies to the whole cycle
            return math.inf
        k = max(bisect.bisect_right(changes, (now + 1e-12, math.inf)) - 1, 0)
        self.asset.set_discharge_rate(changes[k][1])
        return changes[k + 1][0] if k + 1 < len(changes) else math.inf

    def _step(self, dt: float, outflow: dict) -> None:
        """One asset step of ``dt`` [s]; its outflow added to ``outflow`` per tracking id."""
        out = self.asset.step(dt)
        self.largest_step_s = max(self.largest_step_s, dt)
        for tid, m, g in zip(out["tracking_ids"].tolist(), out["masses"].tolist(),
                             out["grades"].tolist()):
            acc = outflow.setdefault(tid, [0.0, 0.0])
            acc[0] += m
            acc[1] += m * g

    def _slice(self, target_time: float, deadline: float, outflow: dict) -> bool:
        """One slice of at most ``slice_s`` towards ``target_time``: its records
        received together, one step over it; shorter than ``slice_s`` where the
        pile holds less than the feeder takes in one (the slice ends before the
        feeder's credit reaches the mass held at its start). False (nothing
        done) where that would not be exact or allowed: the budget is spent,
        nothing is left to step, a record of the slice exists but was not read,
        or the pile holds no more than the feeder's credit, or so little that
        the shorter slice would end before the next record (then the records
        are applied one by one)."""
        asset = self.asset
        start = asset.time
        if start >= target_time - 1e-12 or time.perf_counter() > deadline:
            return False
        end = min(target_time, start + self.o.slice_s, self._setpoint_in_force())
        if end <= start + 1e-12:
            return False
        records, seq = [], self.state.last_applied + 1
        while (record := self.inbox.get(seq)) is not None and record["time"] <= end:
            records.append(record)
            seq += 1
        if record is None and self.server_last_sequence >= seq:
            return False  # an unread record may fall in the slice
        storage = asset.storage
        margin = storage.held_mass() - storage.feeder_credit_kg
        if asset.discharge_rate > 0 and margin > 0 and \
                margin < asset.discharge_rate * (end - start):
            # a small pile: a shorter slice, over which the feeder's credit stays below
            # the mass held at its start (a pile filling up from empty catches up in
            # slices that grow with it, not bin by bin: measured, 65 s of plant time
            # behind at 1,000 bins/s before the pile reached one slice's outflow)
            end = start + margin / asset.discharge_rate * (1.0 - 1e-9)
            while records and records[-1]["time"] > end:
                records.pop()
            if not records:  # it would only shrink the margin: to the next bin, per bin
                return False
        if storage.held_mass() <= storage.feeder_credit_kg + asset.discharge_rate * (end - start):
            return False  # the feeder could reach this slice's arrivals or empty the pile
        if records:
            self._receive_together(records)
        self._step(end - start, outflow)
        return True

    def _receive_together(self, records: list) -> None:
        """Inbound records received in one batch (each at its own time, none before
        the asset's), applied in sequence order."""
        columns = {key: [r[key] for r in records]
                   for key in ("tracking_id", "mass", "grade", "hardness", "source", "time")}
        self.asset.receive_bins(np.array(columns["tracking_id"], dtype=np.uint64),
                                columns["mass"], columns["grade"], columns["hardness"],
                                columns["source"], np.maximum(columns["time"], self.asset.time))
        for r in records:
            del self.inbox[r["sequence"]]
        self.state.last_applied = records[-1]["sequence"]

    def _receive_initial_inventory(self) -> None:
        """The records read so far that are due before the asset's first step (the
        plant's initial inventory, all at its start), received in one batch: the
        pile the plant started with, laid at once (``StorageModel.prefill``)
        rather than one bin at a time."""
        records, seq = [], self.state.last_applied + 1
        while (record := self.inbox.get(seq)) is not None and \
                record["time"] <= self.asset.time + 1e-12:
            records.append(record)
            seq += 1
        if records:
            self._receive_together(records)

    # ------------------------------------------------------------- OPC UA
    async def _connect(self):
        from asyncua import Client, ua
        from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

        from opcua_protocol import APPLICATION_URI_CLIENT

        # asyncua's watchdog probes the server every watchdog_intervall and gives up
        # after as long (1 s by default): on a loaded machine a late answer dropped the
        # session in the middle of a run (bench_opcua, 1,000 bins/s, load 13), though
        # no request of the exchange had timed out. Probe as patiently as a request.
        client = Client(self.o.server_url, timeout=self.o.timeout_s,
                        watchdog_intervall=self.o.timeout_s)
        client.application_uri = APPLICATION_URI_CLIENT
        client.set_user(self.o.username)
        client.set_password(self.o.password)
        if not self.o.insecure:
            if not (self.o.certificate and self.o.private_key):
                raise ValidationError("certificate", "a client certificate and key (or --insecure)")
            await client.set_security(
                SecurityPolicyBasic256Sha256, str(self.o.certificate), str(self.o.private_key),
                server_certificate=str(self.o.server_certificate) if self.o.server_certificate
                else None, mode=ua.MessageSecurityMode.SignAndEncrypt)
        await client.connect()
        return client

    async def _resolve(self, client) -> None:
        from asyncua import ua

        from opcua_protocol import load_nodemap

        self.nodes = {}
        namespaces = await client.get_namespace_array()
        for name, text in load_nodemap(self.o.node_map).items():
            if text.startswith("nsu="):
                uri, _, rest = text[4:].partition(";")
                if uri not in namespaces:
                    raise ValidationError("node_map", f"namespaces the server has ({namespaces})",
                                          f"{name}: unknown namespace {uri!r}")
                text = f"ns={namespaces.index(uri)};{rest}"
            self.nodes[name] = client.get_node(ua.NodeId.from_string(text))

    async def _check_ledger(self) -> None:
        """Go on only with the server ledger this state was exchanged with.

        A server restarted without its ledger restarts its sequence numbers
        and tracking ids: acknowledging or reporting against it would drop
        or misapply bins, so the client stops and says why.
        """
        n = self.nodes
        if "server_instance_id" in n:
            instance = await n["server_instance_id"].read_value()
            if self.server_instance not in (None, instance):
                print(f"stockpile: the server restarted (instance {instance}); continuing on "
                      f"its ledger", file=sys.stderr, flush=True)
            self.server_instance = instance
        if "ledger_id" not in n:
            return
        ledger = await n["ledger_id"].read_value()
        if self.state.ledger_id is None:
            self.state.ledger_id = ledger
        elif ledger != self.state.ledger_id:
            raise LedgerChanged(ValidationError(
                "ledger", f"the server ledger {self.state.ledger_id} this stockpile exchanged with",
                f"the server at {self.o.server_url} has ledger {ledger}: it was restarted "
                f"without its ledger (STATE/ledger.sqlite); start the stockpile from a fresh "
                f"checkpoint to exchange with it"))

    PENDING = ("pending_sequence", "pending_tracking_ids", "pending_masses", "pending_grades",
               "pending_hardness", "pending_sources", "pending_times")

    async def _read_exchange(self) -> tuple:
        """One Read: ``(server time, setpoint, setpoint changes or None)``; the
        unseen pending records go to the inbox."""
        from asyncua import ua

        n = self.nodes
        names = ["simulation_time", "discharge_rate_setpoint", "inbound_last_sequence",
                 "inbound_acknowledged_sequence"]
        history = all(k in n for k in ("setpoint_change_times", "setpoint_change_values"))
        names += ["setpoint_change_times", "setpoint_change_values"] if history else []
        # the pending list holds acknowledged+1 .. last: the first unseen record's index
        acked = max(self.acked, self.server_acked)
        first = 0 if self.need_sync or acked < 0 else max(self.known_sequence - acked, 0)
        params = ua.ReadParameters()
        params.TimestampsToReturn = ua.TimestampsToReturn.Neither
        for name in names + list(self.PENDING):
            item = ua.ReadValueId()
            item.NodeId = n[name].nodeid
            item.AttributeId = ua.AttributeIds.Value
            if name in self.PENDING and first > 0:
                item.IndexRange = f"{first}:{2**31 - 1}"
            params.NodesToRead.append(item)
        results = await self.client.uaclient.read(params)
        for name, result in zip(names, results):
            result.StatusCode.check()
        values = [r.Value.Value for r in results[:len(names)]]
        server_time, setpoint, last_seq, server_acked = values[:4]
        self.server_last_sequence, self.server_acked = int(last_seq), int(server_acked)
        pending = results[len(names):]
        if all(r.StatusCode.value == ua.StatusCodes.BadIndexRangeNoData for r in pending):
            columns = [[]] * len(pending)  # nothing past the first unseen index
        else:
            for result in pending:
                result.StatusCode.check()
            columns = [r.Value.Value or [] for r in pending]
        seq = columns[0]
        if seq and seq[0] > self.known_sequence + 1 and seq[0] > self.state.last_applied + 1:
            self.need_sync = True  # the range started past an unseen record: all next cycle
        else:
            self.need_sync = False
        self._accept_columns(columns)
        return float(server_time), float(setpoint), (values[4:6] if history else None)

    def _accept_columns(self, columns: list) -> None:
        seq, tid, mass, grade, hard, src, t = columns
        self._accept_records([
            {"sequence": int(seq[k]), "tracking_id": int(tid[k]), "mass": float(mass[k]),
             "grade": float(grade[k]), "hardness": float(hard[k]), "source": int(src[k]),
             "time": float(t[k])} for k in range(len(seq))])

    async def _exchange(self) -> float:
        """Send the outbox and acknowledge (after a checkpoint: ``send``), write the
        reported values, read the server's time; return that time."""
        from asyncua import ua

        n = self.nodes
        calls, sent = [], []
        if self._send_now:
            for report in self.state.outbox:
                call = ua.CallMethodRequest()
                call.ObjectId, call.MethodId = n["outbound"].nodeid, n["report_outflow"].nodeid
                call.InputArguments = [
                    ua.Variant(report["sequence"], ua.VariantType.UInt64),
                    ua.Variant(report["tracking_ids"], ua.VariantType.UInt64),
                    ua.Variant(report["masses"], ua.VariantType.Double),
                    ua.Variant(report["grades"], ua.VariantType.Double)]
                calls.append(call)
                sent.append(report)
            acknowledge = self.state.last_applied
            if acknowledge != self.acked:
                call = ua.CallMethodRequest()
                call.ObjectId, call.MethodId = n["sp201"].nodeid, n["acknowledge"].nodeid
                call.InputArguments = [ua.Variant(acknowledge, ua.VariantType.UInt64)]
                calls.append(call)
        requests = [self._report_values(), n["simulation_time"].read_value()]
        if calls:
            requests.insert(0, self.client.uaclient.call(calls))
        # pipelined on one connection: the server answers them in this order
        answers = await asyncio.gather(*requests)
        if calls:
            for k, result in enumerate(answers[0]):
                result.StatusCode.check()  # a refusal: reconnect and resynchronise
                if k < len(sent):
                    log.debug("report %d: %s", sent[k]["sequence"], result.OutputArguments)
                    self.state.outbox.remove(sent[k])
                else:
                    self.acked = acknowledge
        return float(answers[-1])

    def _held_mass_and_grade(self) -> tuple[float, float]:
        """Held mass [kg] and its mass-weighted grade (0 when empty), as
        ``asset.totals()`` gives them, without the rest of the totals (D80, count):
        0.06 ms against 0.23 ms every cycle on a 19,000-particle pile (measured; the
        totals took 20 ms on 12,000 particles before their size distribution was
        summed in one pass)."""
        storage = self.asset.storage
        slots = storage.particles.owned_by(storage.owner)
        mass = storage.particles.mass[slots]
        total = float(mass.sum())
        grade = float((mass * storage.particles.grade[slots]).sum() / total) if total > 0 else 0.0
        return total, grade

    async def _report_values(self) -> None:
        from asyncua import ua

        held_kg, grade = self._held_mass_and_grade()
        self.state.heartbeat += 1
        n = self.nodes
        await self.client.write_values(
            [n["held_mass"], n["average_grade"], n["heartbeat"], n["surrogate_time"]],
            [ua.DataValue(ua.Variant(held_kg, ua.VariantType.Double)),
             ua.DataValue(ua.Variant(grade, ua.VariantType.Double)),
             ua.DataValue(ua.Variant(self.state.heartbeat, ua.VariantType.UInt64)),
             ua.DataValue(ua.Variant(self.asset.time, ua.VariantType.Double))])

    async def cycle(self) -> None:
        """One exchange cycle (see the module docstring)."""
        self.exchange_idle.clear()
        try:
            await self._cycle()
        finally:
            self.exchange_idle.set()

    async def _cycle(self) -> None:
        from asyncua import ua

        n = self.nodes
        if self.o.lockstep:
            await n["plant"].call_method(n["advance_time"],
                                         ua.Variant(float(self.o.period_s), ua.VariantType.Double))
            self.need_sync = True  # deterministic: take the records from the whole list
        server_time, setpoint, changes = await self._read_exchange()
        self.asset.set_discharge_rate(setpoint)
        if changes is not None:
            self.setpoint_changes = sorted(zip(map(float, changes[0] or []),
                                               map(float, changes[1] or [])),
                                           key=lambda change: change[0])  # stable: in order
        # the budget as an attribute: subclasses override advance_to(target_time)
        self._cycle_budget_s = None if self.o.lockstep else self.o.cycle_budget_s
        try:
            self.advance_to(server_time)
        finally:
            self._cycle_budget_s = None
        now = time.monotonic()
        owed = self.state.outbox or self.state.last_applied != self.acked
        self._send_now = bool(owed) and (self.o.lockstep or
                                         now - self._checkpointed_at >= self.o.checkpoint_every_s)
        if self._send_now:
            self._checkpoint()  # only what will be sent or acknowledged needs to be durable
            self._checkpointed_at = now
        server_now = await self._exchange()
        lag = server_now - self.asset.time
        self.lags_s.append(lag)
        self.max_lag_s = max(self.max_lag_s, lag)
        if lag > LAG_WARNING_S and now - self._lag_warned_at > 10.0:
            self._lag_warned_at = now
            print(f"stockpile: not keeping real time: {lag:.1f} s of plant time behind the "
                  f"server (nothing is lost; the exchange catches up)", file=sys.stderr, flush=True)

    async def _session(self) -> None:
        client = await self._connect()
        self.client = client
        try:
            await self._resolve(client)
            await self._check_ledger()
            self.need_sync = True
            self.acked = self.server_acked = -1
            while not self._stop.is_set():
                started = time.monotonic()
                await self.cycle()
                if self._done():
                    self._stop.set()
                    break
                if not self.o.lockstep:
                    remaining = self.o.cycle_s - (time.monotonic() - started)
                    if remaining > 0:
                        try:
                            await asyncio.wait_for(self._stop.wait(), remaining)
                        except TimeoutError:
                            pass
            await self._flush()
        finally:
            try:
                await asyncio.wait_for(client.disconnect(), 2.0)
            except Exception:  # the connection may already be gone
                pass

    async def _flush(self) -> None:
        """On stop: checkpoint, send what is owed and acknowledge (the
        checkpoint interval may have held them back)."""
        if self.state.outbox or self.state.last_applied != self.acked:
            self._checkpoint()
            self._send_now = True
            await self._exchange()

    def _done(self) -> bool:
        # at the end nothing may wait in the outbox or unacknowledged
        return (self.o.duration_s is not None and self.asset.time >= self.o.duration_s - 1e-9
                and not self.state.outbox and self.state.last_applied == self.acked)

    def warm_up(self) -> None:
        """Run a throw-away copy of the asset for ``WARM_UP_S`` before connecting.

        A storage model compiles its numba kernels on their first call
        (measured under CPU load: the first cycle of a ROM stockpile took
        48 s). Its first step calls only some of them: the ROM's surface layer
        lands the first particles 3-4 s after they enter at the inlet, 60 m up,
        and with one step of warm-up a fresh checkout's integration test fell
        6.2 s behind real time there (0.17 s once the kernels were cached). So
        the copy is fed a few bins and run until they have landed and joined
        the bulk, with the feeder drawing: every kernel of a cycle is compiled
        (or loaded from numba's cache) before the exchange starts.
        """
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a small pile is outside any training range
            asset = StockpileAsset(self.o.model, seed=self.o.seed,
                                   particle_mass_kg=self.o.particle_mass_kg,
                                   storage_options=self.o.storage_options)
            asset.set_discharge_rate(100.0)
            for bin_number in range(WARM_UP_BINS):
                asset.receive_bin(1 + bin_number, 500.0, 0.01, 1.0)
                asset.step(self.o.dt_s)
            while asset.time < WARM_UP_S:
                asset.step(self.o.dt_s)

    async def run(self) -> int:
        """Run until stopped (or ``duration_s``), reconnecting after failures."""
        from asyncua import ua

        rest = None
        if self.o.rest_port is not None:
            from surrogate.rest import start_rest

            rest, port = await start_rest(self.asset, "127.0.0.1", self.o.rest_port,
                                          exchange_idle=self.exchange_idle)
            print(f"stockpile: REST on http://127.0.0.1:{port}/", file=sys.stderr, flush=True)
            if self.o.rest_port_file:
                Path(self.o.rest_port_file).write_text(str(port))
        try:
            self.warm_up()
            while not self._stop.is_set():
                try:
                    await self._session()
                except LedgerChanged as exc:
                    print(f"stockpile: {exc}", file=sys.stderr, flush=True)
                    return 1
                except ua.UaStatusCodeError as exc:
                    if exc.code in (ua.StatusCodes.BadUserAccessDenied,
                                    ua.StatusCodes.BadIdentityTokenRejected,
                                    ua.StatusCodes.BadCertificateUntrusted):
                        print(f"stockpile: refused by the server: {exc}", file=sys.stderr)
                        return 1
                    self._lost(exc)
                except (OSError, asyncio.TimeoutError, ConnectionError) as exc:
                    self._lost(exc)
                if not self._stop.is_set():
                    try:
                        await asyncio.wait_for(self._stop.wait(), self.o.reconnect_s)
                    except TimeoutError:
                        pass
        finally:
            self.write_summary()
            if rest is not None:
                await rest.cleanup()
        return 0

    def _lost(self, exc: BaseException) -> None:
        self.reconnects += 1
        print(f"stockpile: connection lost ({type(exc).__name__}: {exc}); reconnecting",
              file=sys.stderr, flush=True)

    def stop(self) -> None:
        self._stop.set()

    def write_summary(self) -> dict:
        """Final state for audits: held mass per tracking id, counters, timing."""
        times = np.array(self.step_times_ms) if self.step_times_ms else np.zeros(1)
        summary = {
            "time_s": self.asset.time, "model": self.asset.model_name, "seed": self.o.seed,
            "last_applied": self.state.last_applied,
            "outflow_sequence": self.state.outflow_sequence,
            "outbox": len(self.state.outbox),
            "held_mass_kg": float(self.asset.particles.mass.sum()),
            "held": {str(k): v for k, v in self.asset.held_by_tracking_id().items()},
            "step_time_p99_ms": float(np.percentile(times, 99)),
            "step_time_mean_ms": float(times.mean()),
            "cycles": len(self.step_times_ms), "cycle_s": self.o.cycle_s,
            "max_lag_s": self.max_lag_s,
            "largest_step_s": self.largest_step_s,
            "lag_p50_s": float(np.percentile(self.lags_s, 50)) if self.lags_s else 0.0,
            "lag_p99_s": float(np.percentile(self.lags_s, 99)) if self.lags_s else 0.0,
            "first_cycle_lag_s": self.lags_s[0] if self.lags_s else 0.0,
            "reconnects": self.reconnects, "history": self.asset.history(),
            # a ROM: the inputs outside its training ranges at its latest check
            "out_of_training_range_now": list(self.asset.storage.out_of_range_now),
        }
        if self.o.summary:
            tmp = Path(f"{self.o.summary}.tmp")
            tmp.write_text(json.dumps(summary, default=_json_default))
            os.replace(tmp, self.o.summary)
        return summary


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(type(value).__name__)
