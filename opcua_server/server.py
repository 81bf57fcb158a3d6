"""The mock 800xA OPC UA server (asyncua) around ``PlantProcess``.

Address space (namespace ``urn:minetwin:mock800xa``, string node ids; the
full list with browse paths is in ``opcua_server/README.md``)::

    Objects/Plant/SimulationTime, Lockstep, AdvanceTime()
    Objects/Plant/CV101/...   incoming belt: BeltSpeed, bins as arrays
    Objects/Plant/SP201/...   DischargeRateSetpoint, reported values,
                              Inbound/ (pending list, Acknowledge()),
                              Outbound/ (ReportOutflow()), LastRefusal
    Objects/Plant/CV301/...   outgoing belt: bins and their contents

Time: in real-time mode the process advances by ``speed`` x the wall-clock
time every ``tick_s``; in lockstep mode it advances only when a client with
the ``surrogate`` role calls ``Plant.AdvanceTime(seconds)``, so a run is
deterministic and independent of the wall clock.

Every refused write or call answers an OPC UA bad status (BadOutOfRange,
BadInvalidArgument, BadSequenceNumberInvalid, BadUserAccessDenied, ...);
method calls also return the message naming the field as their output
argument, and the last refusal's message is readable at
``Plant.SP201.LastRefusal``. Nothing changes on a refusal.
"""

from __future__ import annotations

import asyncio
import copy
import json
import logging
import math
import signal
import sys
import time
import uuid
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
from asyncua import Server, ua
from asyncua.common.events import Event
from asyncua.common.utils import ServiceError
from asyncua.crypto.permission_rules import PermissionRuleset, UserRole
from asyncua.crypto.security_policies import SecurityPolicyNone
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from asyncua.server.address_space import AttributeService
from asyncua.server.history_sql import HistorySQLite

from opcua_server import sessions
from opcua_server.companion import CompanionModel
from opcua_server.ledger_store import LedgerStore
from opcua_server.node_attributes import read_only_variable
from opcua_server.process import MAX_REPORT_ROWS, ExchangeRefused, PlantProcess
from opcua_server.sessions import SessionGuard
from opcua_protocol import APPLICATION_URI_SERVER
from opcua_server.security import (PlantPermissions, PlantUserManager, ensure_certificate,
                                   ensure_users, load_users, pki_paths)

log = logging.getLogger("opcua_server")

SECURE_POLICIES = [
    ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
    ua.SecurityPolicyType.Aes128Sha256RsaOaep_SignAndEncrypt,
    ua.SecurityPolicyType.Aes256Sha256RsaPss_SignAndEncrypt,
]
"""Only SignAndEncrypt endpoints by default (Basic256Sha256 and the Aes policies)."""

EVENT_FIELDS = (("Sequence", ua.VariantType.UInt64), ("TrackingId", ua.VariantType.UInt64),
                ("Mass", ua.VariantType.Double), ("Grade", ua.VariantType.Double),
                ("Hardness", ua.VariantType.Double), ("Source", ua.VariantType.Int32),
                ("DischargeTime", ua.VariantType.Double))
"""Properties of ``BinDischargedEventType`` (mass kg, time s)."""


HISTORIZED = ("Plant.SP201.DischargeRateSetpoint", "Plant.SP201.HeldMass",
              "Plant.SP201.AverageGrade", "Plant.CV101.MassFlow", "Plant.CV101.Totalizer",
              "Plant.CV301.MassFlow", "Plant.CV301.Totalizer")
"""Variables whose history HistoryRead serves (the bin events: ``_History``)."""
MAX_CATCH_UP_S = 0.5
"""Most wall time [s] one tick of the real-time clock advances (x speed)."""
HISTORY_PERIOD = timedelta(hours=6)
"""How far back the history is kept (wall-clock time)."""


BIN_EVENTS_TABLE = """CREATE TABLE IF NOT EXISTS bin_events (
    id INTEGER PRIMARY KEY AUTOINCREMENT, time TEXT NOT NULL, sequence INTEGER NOT NULL,
    tracking_id TEXT NOT NULL, mass REAL NOT NULL, grade REAL NOT NULL, hardness REAL NOT NULL,
    source INTEGER NOT NULL, discharge_time REAL NOT NULL, event_id BLOB NOT NULL,
    message TEXT NOT NULL)"""
"""The BinDischargedEventType events as rows (``time``: the event's Time, ISO UTC;
tracking ids as decimal text, they are uint64)."""


class _History(HistorySQLite):
    """asyncua's SQLite history for the variables, with two fixes (table names
    it accepts for our string node ids: it quotes the id, and its own
    table-name check then refuses the quote; old rows pruned once a minute per
    table instead of by a full scan after every insert, which at 1000 bins/s
    stalled the server), and the bin events in a table of their own.

    The bin events are not asyncua's event history: that one decodes every
    event through an internal subscription and commits per event (1.5 ms per
    event in the server's loop, profiled at 1000 bins/s). Here the server
    hands over the events of one tick (``save_bin_events``: one insert of all
    rows, one commit), and HistoryReadEvents of SP201, Plant or the Server
    object (the notifier chain they reach) reads them back (``make_event``
    builds each event from its row)."""

    PRUNE_EVERY_S = 60.0

    def __init__(self, path: str, bin_event_sources=(), make_event=None,
                 period: timedelta = timedelta(hours=6)):
        super().__init__(path)
        self._pruned_at: dict[str, float] = {}
        self.bin_event_sources = set(bin_event_sources)
        self.make_event = make_event
        self.period = period

    async def init(self) -> None:
        await super().init()
        await self._db.execute(BIN_EVENTS_TABLE)
        await self._db.commit()

    def _due(self, table: str) -> bool:
        now = time.monotonic()
        if now - self._pruned_at.get(table, -math.inf) < self.PRUNE_EVERY_S:
            return False
        self._pruned_at[table] = now
        return True

    def _get_table_name(self, node_id: ua.NodeId) -> str:
        name = f"{node_id.NamespaceIndex}_{node_id.Identifier}"
        return "".join(c if c.isalnum() else "_" for c in name)

    async def execute_sql_delete(self, condition, args, table, node_id) -> None:
        if self._due(table):
            await super().execute_sql_delete(condition, args, table, node_id)

    async def save_bin_events(self, rows: list[tuple]) -> None:
        """Rows ``(time, sequence, tracking id, mass, grade, hardness, source,
        discharge time, event id, message)`` of one tick, in one transaction."""
        await self._db.executemany("INSERT INTO bin_events VALUES (NULL, ?, ?, ?, ?, ?, ?, ?, "
                                   "?, ?, ?)", rows)
        if self._due("bin_events"):
            limit = (datetime.now(timezone.utc) - self.period).isoformat(" ")
            await self._db.execute("DELETE FROM bin_events WHERE time < ?", (limit,))
        await self._db.commit()

    async def read_event_history(self, source_id, start, end, nb_values, evfilter):
        if source_id not in self.bin_event_sources:
            return await super().read_event_history(source_id, start, end, nb_values, evfilter)
        start_time, end_time, order, limit = self._get_bounds(start, end, nb_values)
        async with self._db.execute(
                "SELECT time, sequence, tracking_id, mass, grade, hardness, source, "
                f"discharge_time, event_id, message FROM bin_events WHERE time BETWEEN ? AND ? "
                f"ORDER BY id {order} LIMIT ?", (start_time, end_time, limit)) as cursor:
            rows = await cursor.fetchall()
        cut = self.max_history_data_response_size
        cont = datetime.fromisoformat(rows[cut][0]) if len(rows) > cut else None
        return [self.make_event(row) for row in rows[:cut]], cont


@dataclass
class Writable:
    """A variable clients may write: the roles allowed and what a write does."""

    roles: tuple[str, ...]
    apply: callable
    variant: ua.VariantType = ua.VariantType.Double


@dataclass
class Refusals:
    count: int = 0
    last: str = ""
    by_status: dict = field(default_factory=dict)


class PlantAttributeService(AttributeService):
    """Writes checked per node and per role, values validated before they land."""

    def __init__(self, aspace, plant: "PlantServer"):
        super().__init__(aspace)
        self.plant = plant

    async def write(self, params, user=None):
        if user is None or user.role == UserRole.Admin:  # the server's own writes
            return await super().write(params, user) if user else await super().write(params)
        results = []
        role = getattr(user, "plant_role", None)
        for item in params.NodesToWrite:
            target = self.plant.writable.get(item.NodeId)
            if target is None or role not in target.roles or item.AttributeId != ua.AttributeIds.Value:
                await self.plant.refuse("BadUserAccessDenied",
                                  f"{item.NodeId.to_string()}: not writable by role {role!r}")
                results.append(ua.StatusCode(ua.StatusCodes.BadUserAccessDenied))
                continue
            variant = item.Value.Value if item.Value else None
            value = variant.Value if variant is not None else None
            try:
                if variant is None or variant.VariantType != target.variant or \
                        isinstance(value, (list, tuple, np.ndarray)) or value is None:
                    got = variant.VariantType.name if variant is not None else "no value"
                    raise ExchangeRefused("BadTypeMismatch", item.NodeId.Identifier,
                                          f"a scalar {target.variant.name}", f"got {got}")
                async with self.plant._lock:  # no exchange call runs between the two
                    target.apply(value)
                    await self.plant.store.save_async(self.plant.process)
            except ExchangeRefused as exc:
                await self.plant.refuse(exc.status, exc.message)
                results.append(ua.StatusCode(getattr(ua.StatusCodes, exc.status)))
                continue
            except (TypeError, ValueError) as exc:
                await self.plant.refuse("BadTypeMismatch", f"{item.NodeId.Identifier}: {exc}")
                results.append(ua.StatusCode(ua.StatusCodes.BadTypeMismatch))
                continue
            now = _now()
            stored = ua.DataValue(ua.Variant(self.plant.coerce(value, target.variant),
                                             target.variant), SourceTimestamp=now,
                                  ServerTimestamp=now)
            results.append(await self._aspace.write_attribute_value(
                item.NodeId, ua.AttributeIds.Value, stored))
            await self.plant.publish_setpoint_changes()  # with the setpoint, at once
        return results


class RefuseNoneChannel:
    """Policy factory for None secure channels when no None endpoint is offered.

    asyncua 2.1.0 accepts OpenSecureChannel with SecurityPolicy#None even when
    no None endpoint is offered (the connection starts with a None policy and
    ``select_policy`` keeps it when nothing matches), and such a channel skips
    the permission ruleset entirely (measured: a viewer could read over it).
    Discovery needs the None channel (clients call GetEndpoints on it first),
    so this factory, first in the server's policy list, gives None channels a
    ruleset that refuses every request but discovery.
    """

    def matches(self, uri, mode=None) -> bool:
        return uri == SecurityPolicyNone.URI

    def create(self, peer_certificate):
        return SecurityPolicyNone(peer_certificate, permission_ruleset=DiscoveryOnly())


class DiscoveryOnly(PermissionRuleset):
    """On a None channel only discovery (GetEndpoints, FindServers) is served:
    asyncua exempts those and session creation from the ruleset; every other
    request, whoever the user, is refused with BadUserAccessDenied."""

    def check_validity(self, user, action_type_id, body) -> bool:
        log.warning("refused a request on an unencrypted (None) secure channel")
        return False


class TrustListValidator:
    """Accept a client certificate only if a copy is in the trust list folder.

    The folder is read at every new secure channel, so dropping a client's
    certificate into it takes effect without a restart; time range and
    application URI are checked too.
    """

    OPTIONS = (CertificateValidatorOptions.TIME_RANGE | CertificateValidatorOptions.URI
               | CertificateValidatorOptions.TRUSTED | CertificateValidatorOptions.PEER_CLIENT)

    def __init__(self, folder: Path):
        self.folder = Path(folder)

    async def __call__(self, certificate, app_description) -> None:
        if not any(p.suffix in (".der", ".pem", ".crt") for p in self.folder.glob("*")):
            log.warning("refused client certificate: the trust list %s is empty", self.folder)
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)
        store = TrustStore([self.folder], [])
        await store.load()
        try:
            await CertificateValidator(self.OPTIONS, store).validate(certificate, app_description)
        except ServiceError:
            log.warning("refused client certificate %s", certificate.subject.rfc4514_string())
            raise


class ListenError(Exception):
    """The server could not listen on its host and port."""


class _StartErrorShownByCaller(logging.Filter):
    """asyncua logs a failed start (a port in use) with a traceback and then raises
    it; ``serve-800xa`` reports the same error in one line."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "error starting server" not in record.getMessage()


class PlantServer:
    """asyncua server publishing a ``PlantProcess``.

    Parameters
    ----------
    config : dict
        Validated configuration (``opcua_server.config.load_config``).
    speed : float
        Simulation seconds per wall-clock second (real time = 1).
    insecure : bool
        Also offer the None security endpoint (local development only).
    lockstep : bool
        Advance only through ``Plant.AdvanceTime`` calls.
    """

    def __init__(self, config: dict, *, speed: float = 1.0, insecure: bool = False,
                 lockstep: bool = False, until_s: float | None = None):
        self.config = config
        self.until_s = until_s
        self.on_until = None  # called once when the clock reaches until_s
        self.speed = float(speed)
        self.insecure = insecure
        self.lockstep = lockstep
        self.process = PlantProcess(config)
        self._published_setpoint = self.process.discharge_rate_setpoint
        self._published_change = self.process.setpoint_changes[-1]
        self.instance_id = str(uuid.uuid4())
        self._flows_published_at = -math.inf
        self._slow_warned_at = -math.inf
        srv = config["server"]
        self.host, self.port = srv["host"], int(srv["port"])
        self.state_dir = Path(srv["state_dir"])
        self.uri = srv["namespace_uri"]
        self.endpoint = f"opc.tcp://{self.host}:{self.port}/minetwin/"
        self.refusals = Refusals()
        self.writable: dict[ua.NodeId, Writable] = {}
        self.max_surrogate_lag_s = 0.0
        self.surrogate_time = None
        self.paused = False
        self._stop = asyncio.Event()
        self._lock = asyncio.Lock()

    # ---------------------------------------------------------------- set-up
    def nid(self, name: str) -> ua.NodeId:
        return ua.NodeId(name, self.idx)

    async def start(self) -> None:
        server = Server()
        self.server = server
        server.iserver.bind_condition_methods = True  # ConditionRefresh, as generic clients call it
        await server.init()
        users_file = self.state_dir / "users.toml"
        created = ensure_users(users_file)
        if created:
            print(f"serve-800xa: created {users_file} with random passwords; they are in {created}",
                  file=sys.stderr)
        server.iserver.user_manager = PlantUserManager(load_users(users_file))
        server.iserver.attribute_service = PlantAttributeService(server.iserver.aspace, self)
        server.set_endpoint(self.endpoint)
        server.set_server_name("MineTwin mock 800xA process simulator")
        await server.set_application_uri(APPLICATION_URI_SERVER)
        server.set_identity_tokens([ua.UserNameIdentityToken])
        pki = pki_paths(self.state_dir)
        replacing = pki["cert"].exists()
        if await ensure_certificate(pki["key"], pki["cert"], APPLICATION_URI_SERVER, client=False,
                                    endpoint_host=self.host):
            print(f"serve-800xa: replaced the server certificate {pki['cert']} (it had expired or "
                  f"lacked a name of this host; a client that pinned the old one needs this one)"
                  if replacing else
                  f"serve-800xa: generated a self-signed server certificate {pki['cert']}",
                  file=sys.stderr)
        pki["trusted"].mkdir(parents=True, exist_ok=True)
        await server.load_certificate(str(pki["cert"]))
        await server.load_private_key(str(pki["key"]))
        server.set_certificate_validator(TrustListValidator(pki["trusted"]))
        self.idx = await server.register_namespace(self.uri)
        self.store = LedgerStore(self.state_dir / "ledger.sqlite")
        if self.store.load(self.process):
            p = self.process
            print(f"serve-800xa: resumed ledger {self.store.ledger_id} ({self.store.path}) at "
                  f"t={p.time:.3f} s: last inbound {p.last_sequence}, acknowledged "
                  f"{p.acknowledged_sequence}, {len(p.pending)} pending, outbound "
                  f"{p.outbound_sequence}, next tracking id {p.next_tracking_id}",
                  file=sys.stderr, flush=True)
            self._published_setpoint = p.discharge_rate_setpoint
            self._published_change = p.setpoint_changes[-1]
        self.store.save(self.process, force=True)
        await self._build_address_space()
        policies = list(SECURE_POLICIES)
        if self.insecure:
            policies.insert(0, ua.SecurityPolicyType.NoSecurity)
            banner = "!" * 72
            print(f"{banner}\nWARNING: --insecure: the None security endpoint is ON; messages are "
                  f"neither signed nor encrypted.\nLocal development only.\n{banner}", file=sys.stderr)
        server.set_security_policy(policies, permission_ruleset=PlantPermissions(self._methods_by_role))
        sessions.install()
        server.iserver.plant_guard = SessionGuard(
            writable_roles={node: w.roles for node, w in self.writable.items()},
            methods_by_role=self._methods_by_role, allow_none_sessions=self.insecure)
        if not self.insecure:
            server._policies.insert(0, RefuseNoneChannel())
        start_error = _StartErrorShownByCaller()
        logging.getLogger("asyncua.server.server").addFilter(start_error)
        try:
            await server.start()
        except OSError as exc:  # the port is taken, or the host is not this machine's
            raise ListenError(f"cannot serve on {self.host}:{self.port}: {exc}") from None
        finally:
            logging.getLogger("asyncua.server.server").removeFilter(start_error)
        await self._start_history()
        await self.publish()

    async def _build_address_space(self) -> None:
        s, idx, nid = self.server, self.idx, self.nid
        objects = s.nodes.objects
        p = self.process
        plant = await objects.add_object(nid("Plant"), ua.QualifiedName("Plant", idx))
        self.plant_node = plant
        await _describe(plant, "the mock 800xA plant: CV101 -> SP201 -> CV301")
        self.companion = CompanionModel(s, idx, _eu_information, self._write)
        await self.companion.add_types()

        async def var(parent, name, value, vtype, description, *, unit=None, eu_range=None,
                      dims=None, writable=None):
            """A variable with its description; ``unit`` (a UNITS key) makes it an
            AnalogUnitType, with ``eu_range`` an AnalogItemType (both with
            EngineeringUnits); ``dims`` a one-dimensional array of that many
            elements (0: any length)."""
            node = await self._add_variable(parent, nid(name), name.split(".")[-1], value, vtype,
                                            description, unit, eu_range, dims)
            if writable is not None:
                await node.set_writable()
                self.writable[node.nodeid] = writable
            return node

        D, U, I, S, B = (ua.VariantType.Double, ua.VariantType.UInt64, ua.VariantType.Int32,
                         ua.VariantType.String, ua.VariantType.Boolean)
        await var(plant, "Plant.SimulationTime", 0.0, D, "simulation time of the plant",
                  unit="s")
        await var(plant, "Plant.Lockstep", self.lockstep, B,
                  "true if the clock moves only by AdvanceTime")
        await var(plant, "Plant.LedgerId", self.store.ledger_id, S,
                  "identity of the plant's durable ledger (STATE/ledger.sqlite); "
                  "the same across restarts that kept it")
        await var(plant, "Plant.ServerInstanceId", self.instance_id, S,
                  "new at every start of the server process")
        self._advance_node = await plant.add_method(
            nid("Plant.AdvanceTime"), ua.QualifiedName("AdvanceTime", idx),
            self._method((("seconds", D, False),), self._advance_time),
            [_arg("seconds", ua.ObjectIds.Double, "simulation seconds to advance")],
            [_arg("simulation_time", ua.ObjectIds.Double, "new simulation time [s]")])

        def belt(b, top, name):
            return (
                ("BeltSpeed", b.speed_m_s, D, "belt speed", "m/s", (0.0, top), None,
                 Writable(("operator",), lambda v: p.set_belt_speed(name, v))),
                ("BinLength", b.bin_length_m, D, "length of one bin", "m", None, None, None))

        cv101 = await plant.add_object(nid("Plant.CV101"), ua.QualifiedName("CV101", idx),
                                       objecttype=self.companion.belt_type())
        await _describe(cv101, "incoming conveyor, discharges onto SP201 (bins of the belt)")
        n1, n3 = p.cv101.n_bins, p.cv301.n_bins
        for row in belt(p.cv101, p.max_belt_speed["cv101"], "cv101") + (
                ("BinTrackingIds", [], U, "tracking id per bin, loading point first (0 = empty)",
                 None, None, n1, None),
                ("BinMasses", [], D, "mass per bin, loading point first", "kg", None, n1, None),
                ("BinGrades", [], D, "ore grade (mass fraction) per bin", "1", (0.0, 1.0), n1,
                 None),
                ("BinHardness", [], D, "hardness index per bin", None, None, n1, None),
                ("BinSources", [], I, "source index per bin (-1 = empty)", None, None, n1, None),
                ("BinPositions", [], D, "bin centres from the loading point", "m", None, n1,
                 None),
                ("Mass", 0.0, D, "mass on the belt", "kg", None, None, None),
                ("MassFlow", 0.0, D, "belt scale at the head: mass flow discharged onto SP201, "
                 "averaged over the last 10 s", "kg/s", None, None, None),
                ("Totalizer", 0.0, D, "belt scale at the head: total mass discharged onto SP201",
                 "kg", None, None, None)):
            name, value, vtype, text, unit, eu_range, dims, writable = row
            await var(cv101, f"Plant.CV101.{name}", value, vtype, text, unit=unit,
                      eu_range=eu_range, dims=dims, writable=writable)
        await self.companion.add_belt_scale("CV101", "at the head (discharge onto SP201)")

        sp = await plant.add_object(nid("Plant.SP201"), ua.QualifiedName("SP201", idx))
        self.sp201_node = sp
        await _describe(sp, "stockpile: feeder setpoint, the values the stockpile reports and "
                            "the loss-free exchange; emits BinDischargedEventType")
        top = p.max_discharge_rate
        await var(sp, "Plant.SP201.DischargeRateSetpoint", p.discharge_rate_setpoint, D,
                  "feeder discharge-rate setpoint", unit="kg/s", eu_range=(0.0, top),
                  writable=Writable(("operator",), p.set_discharge_rate))
        await var(sp, "Plant.SP201.SetpointChangeTimes", [0.0], D,
                  "plant time at which each of the latest setpoints took effect", unit="s",
                  dims=0)
        await var(sp, "Plant.SP201.SetpointChangeValues", [p.discharge_rate_setpoint], D,
                  "the latest setpoints, one per SetpointChangeTimes entry", unit="kg/s",
                  eu_range=(0.0, top), dims=0)
        await var(sp, "Plant.SP201.HeldMass", 0.0, D, "mass held, reported by the stockpile",
                  unit="kg", writable=Writable(("surrogate",),
                                               lambda v: _check("HeldMass", v, 0.0, math.inf)))
        await var(sp, "Plant.SP201.AverageGrade", 0.0, D,
                  "average ore grade (mass fraction) reported by the stockpile", unit="1",
                  eu_range=(0.0, 1.0),
                  writable=Writable(("surrogate",), lambda v: _check("AverageGrade", v, 0.0, 1.0)))
        await var(sp, "Plant.SP201.Heartbeat", 0, U,
                  "stockpile heartbeat counter, +1 per exchange cycle",
                  writable=Writable(("surrogate",), lambda v: _check("Heartbeat", v, 0, 2**64 - 1),
                                    ua.VariantType.UInt64))
        await var(sp, "Plant.SP201.SurrogateTime", 0.0, D,
                  "the stockpile's simulation time (lag = SimulationTime - this)", unit="s",
                  writable=Writable(("surrogate",), self._surrogate_time))
        await var(sp, "Plant.SP201.LastRefusal", "", S,
                  "Status: field: must be ... (got ...) of the last refused write or call")
        inbound = await sp.add_object(nid("Plant.SP201.Inbound"), ua.QualifiedName("Inbound", idx))
        await _describe(inbound, "bins discharged onto SP201, pending until acknowledged")
        await var(inbound, "Plant.SP201.Inbound.LastSequence", 0, U,
                  "last inbound sequence number given")
        await var(inbound, "Plant.SP201.Inbound.AcknowledgedSequence", 0, U,
                  "highest sequence number acknowledged by the stockpile")
        for name, vtype, text, unit, eu_range in (
                ("PendingSequence", U, "sequence number of each pending record", None, None),
                ("PendingTrackingIds", U, "tracking id of each pending record", None, None),
                ("PendingMasses", D, "mass of each pending record", "kg", None),
                ("PendingGrades", D, "ore grade (mass fraction) of each pending record", "1",
                 (0.0, 1.0)),
                ("PendingHardness", D, "hardness index of each pending record", None, None),
                ("PendingSources", I, "source index of each pending record", None, None),
                ("PendingTimes", D, "discharge time of each pending record", "s", None)):
            await var(inbound, f"Plant.SP201.Inbound.{name}", [], vtype, text, unit=unit,
                      eu_range=eu_range, dims=0)
        self._ack_node = await inbound.add_method(
            nid("Plant.SP201.Inbound.Acknowledge"), ua.QualifiedName("Acknowledge", idx),
            self._method((("sequence", U, False),), self._acknowledge),
            [_arg("sequence", ua.ObjectIds.UInt64, "highest sequence number applied")],
            [_arg("message", ua.ObjectIds.String, "result")])
        outbound = await sp.add_object(nid("Plant.SP201.Outbound"), ua.QualifiedName("Outbound", idx))
        await _describe(outbound, "outflow of SP201 onto CV301, one report per number")
        await var(outbound, "Plant.SP201.Outbound.LastSequence", 0, U,
                  "last outflow report number applied")
        self._report_node = await outbound.add_method(
            nid("Plant.SP201.Outbound.ReportOutflow"), ua.QualifiedName("ReportOutflow", idx),
            self._method((("sequence", U, False), ("tracking_ids", U, True),
                          ("masses", D, True), ("grades", D, True)), self._report),
            [_arg("sequence", ua.ObjectIds.UInt64, "outflow report number, 1, 2, ..."),
             _arg("tracking_ids", ua.ObjectIds.UInt64, "tracking ids", array=True),
             _arg("masses", ua.ObjectIds.Double, "mass [kg] per tracking id", array=True),
             _arg("grades", ua.ObjectIds.Double, "grade [-] per tracking id", array=True)],
            [_arg("message", ua.ObjectIds.String, "applied / already applied / refusal")])

        cv301 = await plant.add_object(nid("Plant.CV301"), ua.QualifiedName("CV301", idx),
                                       objecttype=self.companion.belt_type())
        await _describe(cv301, "outgoing conveyor, loaded at SP201's outlet (bins of the belt)")
        for row in belt(p.cv301, p.max_belt_speed["cv301"], "cv301") + (
                ("BinMasses", [], D, "mass per bin, loading point first", "kg", None, n3, None),
                ("BinGrades", [], D, "ore grade (mass fraction) per bin", "1", (0.0, 1.0), n3,
                 None),
                ("BinPositions", [], D, "bin centres from the loading point", "m", None, n3,
                 None),
                ("ContentsBin", [], I, "bin index of each (bin, tracking id) row", None, None,
                 0, None),
                ("ContentsTrackingIds", [], U, "tracking id of each (bin, tracking id) row",
                 None, None, 0, None),
                ("ContentsMasses", [], D, "mass of each (bin, tracking id) row", "kg", None, 0,
                 None),
                ("Mass", 0.0, D, "mass on the belt", "kg", None, None, None),
                ("Grade", 0.0, D, "average ore grade (mass fraction) on the belt", "1",
                 (0.0, 1.0), None, None),
                ("DeliveredMass", 0.0, D, "mass delivered at the end of the belt", "kg", None,
                 None, None),
                ("MassFlow", 0.0, D, "belt scale at the loading point: mass flow loaded from "
                 "SP201, averaged over the last 10 s", "kg/s", None, None, None),
                ("Totalizer", 0.0, D, "belt scale at the loading point: total mass loaded from "
                 "SP201", "kg", None, None, None)):
            name, value, vtype, text, unit, eu_range, dims, writable = row
            await var(cv301, f"Plant.CV301.{name}", value, vtype, text, unit=unit,
                      eu_range=eu_range, dims=dims, writable=writable)
        await self.companion.add_belt_scale("CV301", "at the loading point (outflow of SP201)")
        await self.companion.add_feed_lots(plant, p.lots)

        etype = await s.nodes.base_event_type.add_object_type(
            nid("BinDischargedEventType"), ua.QualifiedName("BinDischargedEventType", idx))
        for name, vtype in EVENT_FIELDS:
            await etype.add_property(nid(f"BinDischargedEventType.{name}"),
                                     ua.QualifiedName(name, idx), ua.get_default_value(vtype),
                                     varianttype=vtype)
        self.event_generator = await s.get_event_generator(etype, sp)
        # the notifier chain Server -> Plant -> SP201: a generic client subscribed to
        # the Server object (UaExpert's event view) gets the bins too
        await plant.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
        await s.nodes.server.add_reference(plant.nodeid, ua.ObjectIds.HasNotifier)
        await plant.add_reference(sp.nodeid, ua.ObjectIds.HasNotifier)
        self._notifiers = (plant.nodeid, s.nodes.server.nodeid)
        for method, text in (
                (self._advance_node, "lockstep only: advance the plant by seconds; returns the "
                                     "new simulation time"),
                (self._ack_node, "drop the pending records up to sequence (the stockpile has "
                                 "applied them)"),
                (self._report_node, "apply one outflow report once (tracking ids, masses [kg], "
                                    f"grades) onto CV301; at most {MAX_REPORT_ROWS} tracking ids")):
            await _describe(method, text)
        refresh = {ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh),
                   ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh2)}
        self._methods_by_role = {
            "surrogate": {self._ack_node.nodeid, self._report_node.nodeid, self._advance_node.nodeid,
                          *refresh},
            "operator": set(refresh), "viewer": set(refresh)}

    async def _start_history(self) -> None:
        """HistoryRead of the setpoint, the stockpile's reported values and the belt
        scales, and HistoryReadEvents of the bin events on SP201, Plant and the
        Server object, kept ``HISTORY_PERIOD`` in ``STATE/history.sqlite``
        (WAL; see ``_History``)."""
        notifiers = (self.sp201_node.nodeid,) + self._notifiers
        history = _History(str(self.state_dir / "history.sqlite"), notifiers,
                           self._history_event, HISTORY_PERIOD)
        await history.init()
        await history._db.execute("PRAGMA journal_mode=WAL")
        await history._db.execute("PRAGMA synchronous=NORMAL")
        self.history = history
        self.server.iserver.history_manager.set_storage(history)
        await self.server.historize_node_data_change(
            [self.server.get_node(self.nid(name)) for name in HISTORIZED], period=HISTORY_PERIOD)
        for node in notifiers:  # HistoryRead: generic clients offer the event history
            await self.server.get_node(node).set_event_notifier(
                [ua.EventNotifier.SubscribeToEvents, ua.EventNotifier.HistoryRead])

    def _history_event(self, row: tuple) -> Event:
        """One BinDischargedEventType event of the history, from its row."""
        when, seq, tid, mass, grade, hardness, source, discharged, event_id, message = row
        when = datetime.fromisoformat(when)
        template, V = self.event_generator.event, ua.VariantType
        event = Event()
        for name, value, vtype in (
                ("EventId", event_id, V.ByteString), ("EventType", template.EventType, V.NodeId),
                ("SourceNode", template.SourceNode, V.NodeId),
                ("SourceName", template.SourceName, V.String), ("Time", when, V.DateTime),
                ("ReceiveTime", when, V.DateTime),
                ("Message", ua.LocalizedText(message), V.LocalizedText),
                ("Severity", template.Severity, V.UInt16), ("Sequence", seq, V.UInt64),
                ("TrackingId", int(tid), V.UInt64), ("Mass", mass, V.Double),
                ("Grade", grade, V.Double), ("Hardness", hardness, V.Double),
                ("Source", source, V.Int32), ("DischargeTime", discharged, V.Double)):
            event.add_property(name, value, vtype)
        return event

    async def _add_variable(self, parent, nodeid, name, value, vtype, description, unit,
                            eu_range, dims):
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = nodeid
        item.BrowseName = ua.QualifiedName(name, self.idx)
        item.NodeClass = ua.NodeClass.Variable
        item.ParentNodeId = parent.nodeid
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasComponent)
        item.TypeDefinition = ua.NodeId(
            ua.ObjectIds.AnalogItemType if eu_range is not None else
            ua.ObjectIds.AnalogUnitType if unit is not None else ua.ObjectIds.BaseDataVariableType)
        attrs = read_only_variable(name, description, value, vtype, dims)
        item.NodeAttributes = attrs
        result = (await self.server.iserver.isession.add_nodes([item]))[0]
        result.StatusCode.check()
        node = self.server.get_node(nodeid)
        now = _now()  # timestamps from the start, also on values that never change
        await self.server.write_attribute_value(nodeid, ua.DataValue(
            ua.Variant(value, vtype), SourceTimestamp=now, ServerTimestamp=now))
        if unit is not None:
            await node.add_property(ua.NodeId(f"{nodeid.Identifier}.EngineeringUnits", self.idx),
                                    ua.QualifiedName("EngineeringUnits", 0),
                                    ua.Variant(_eu_information(unit)),
                                    datatype=ua.NodeId(ua.ObjectIds.EUInformation))
        if eu_range is not None:
            await node.add_property(ua.NodeId(f"{nodeid.Identifier}.EURange", self.idx),
                                    ua.QualifiedName("EURange", 0),
                                    ua.Variant(ua.Range(*map(float, eu_range))),
                                    datatype=ua.NodeId(ua.ObjectIds.Range))
        return node

    # ---------------------------------------------------------------- values
    @staticmethod
    def coerce(value, vtype):
        return int(value) if vtype == ua.VariantType.UInt64 else float(value)

    async def _write(self, name: str, value, vtype) -> None:
        now = _now()
        await self.server.write_attribute_value(self.nid(name), ua.DataValue(
            ua.Variant(value, vtype), SourceTimestamp=now, ServerTimestamp=now))

    async def publish(self) -> None:
        """Copy the process state into the address space."""
        p, D, U, I = (self.process, ua.VariantType.Double, ua.VariantType.UInt64,
                      ua.VariantType.Int32)
        w = self._write
        if p.discharge_rate_setpoint != self._published_setpoint:  # the scheduled start
            await w("Plant.SP201.DischargeRateSetpoint", p.discharge_rate_setpoint, D)
            self._published_setpoint = p.discharge_rate_setpoint
        await self.publish_setpoint_changes()
        b = p.cv101
        await w("Plant.CV101.BinTrackingIds", b.tracking_id.tolist(), U)
        await w("Plant.CV101.BinMasses", b.mass.tolist(), D)
        await w("Plant.CV101.BinGrades", b.grade.tolist(), D)
        await w("Plant.CV101.BinHardness", b.hardness.tolist(), D)
        await w("Plant.CV101.BinSources", b.source.tolist(), I)
        await w("Plant.CV101.BinPositions", b.positions().tolist(), D)
        await w("Plant.CV101.Mass", float(b.mass.sum()), D)
        await self._publish_inbound()
        c = p.cv301
        await w("Plant.CV301.BinMasses", c.mass.tolist(), D)
        await w("Plant.CV301.BinGrades", c.grade.tolist(), D)
        await w("Plant.CV301.BinPositions", c.positions().tolist(), D)
        slots, tids, masses = [], [], []
        for slot, contents in enumerate(p.cv301_contents):
            for tid, m in contents.items():
                slots.append(slot), tids.append(tid), masses.append(m)
        await w("Plant.CV301.ContentsBin", slots, I)
        await w("Plant.CV301.ContentsTrackingIds", tids, U)
        await w("Plant.CV301.ContentsMasses", masses, D)
        total = float(c.mass.sum())
        await w("Plant.CV301.Mass", total, D)
        await w("Plant.CV301.Grade", float(c.mass @ c.grade / total) if total > 0 else 0.0, D)
        await w("Plant.CV301.DeliveredMass", p.delivered_mass_kg, D)
        now = time.monotonic()
        if self.lockstep or now - self._flows_published_at >= 1.0:  # 10 s averages: 1/s
            self._flows_published_at = now
            for belt, totalizer in (("cv101", p.mass_in_kg), ("cv301", p.mass_out_kg)):
                await w(f"Plant.{belt.upper()}.MassFlow", p.mass_flow(belt), D)
                await w(f"Plant.{belt.upper()}.Totalizer", totalizer, D)
            await self.companion.publish(p)
        # the clock last: a client that reads time T in one Read also reads every
        # record discharged up to T (writes of historized values may yield between)
        await w("Plant.SimulationTime", p.time, D)

    async def publish_setpoint_changes(self) -> None:
        changes, D = self.process.setpoint_changes, ua.VariantType.Double
        if changes[-1] != self._published_change:
            await self._write("Plant.SP201.SetpointChangeTimes", [t for t, _ in changes], D)
            await self._write("Plant.SP201.SetpointChangeValues", [v for _, v in changes], D)
            self._published_change = changes[-1]

    async def _publish_inbound(self) -> None:
        p, D, U, I = (self.process, ua.VariantType.Double, ua.VariantType.UInt64,
                      ua.VariantType.Int32)
        pend = p.pending_arrays()
        w = self._write
        await w("Plant.SP201.Inbound.PendingSequence", pend["sequence"].tolist(), U)
        await w("Plant.SP201.Inbound.PendingTrackingIds", pend["tracking_id"].tolist(), U)
        await w("Plant.SP201.Inbound.PendingMasses", pend["mass"].tolist(), D)
        await w("Plant.SP201.Inbound.PendingGrades", pend["grade"].tolist(), D)
        await w("Plant.SP201.Inbound.PendingHardness", pend["hardness"].tolist(), D)
        await w("Plant.SP201.Inbound.PendingSources", pend["source"].tolist(), I)
        await w("Plant.SP201.Inbound.PendingTimes", pend["time"].tolist(), D)
        await w("Plant.SP201.Inbound.LastSequence", p.last_sequence, U)
        await w("Plant.SP201.Inbound.AcknowledgedSequence", p.acknowledged_sequence, U)
        await w("Plant.SP201.Outbound.LastSequence", p.outbound_sequence, U)

    async def refuse(self, status: str, message: str) -> None:
        self.refusals.count += 1
        self.refusals.last = f"{status}: {message}"
        self.refusals.by_status[status] = self.refusals.by_status.get(status, 0) + 1
        await self._write("Plant.SP201.LastRefusal", self.refusals.last, ua.VariantType.String)
        log.warning("refused: %s", self.refusals.last)

    def _surrogate_time(self, value) -> None:
        value = _check("SurrogateTime", value, 0.0, math.inf)
        self.surrogate_time = value
        self.max_surrogate_lag_s = max(self.max_surrogate_lag_s, self.process.time - value)

    # --------------------------------------------------------------- advance
    async def advance(self, dt: float) -> None:
        if self.until_s is not None:  # the clock stops at until_s exactly
            dt = min(dt, max(self.until_s - self.process.time, 0.0))
        async with self._lock:
            records = self.process.advance(dt)
            await self.store.save_async(self.process)  # durable before anyone sees it
            await self.publish()
        if self.until_s is not None and not self.paused and \
                self.process.time >= self.until_s - 1e-9:
            self.pause()
            if self.on_until is not None:
                self.on_until()
        ev, rows = self.event_generator, []
        for r in records:
            ev.event.Sequence = ua.Variant(r.sequence, ua.VariantType.UInt64)
            ev.event.TrackingId = ua.Variant(r.tracking_id, ua.VariantType.UInt64)
            ev.event.Mass = r.mass_kg
            ev.event.Grade = r.grade
            ev.event.Hardness = r.hardness
            ev.event.Source = ua.Variant(r.source, ua.VariantType.Int32)
            ev.event.DischargeTime = r.time_s
            message = f"bin {r.tracking_id} discharged onto SP201 (seq {r.sequence})"
            await ev.trigger(message=message)
            rows.append((ev.event.Time.isoformat(" "), r.sequence, str(r.tracking_id), r.mass_kg,
                         r.grade, r.hardness, r.source, r.time_s, ev.event.EventId.Value, message))
            for notifier in self._notifiers:  # the same event, up the notifier chain
                event = copy.copy(ev.event)  # a copy: the generator's event stays SP201's
                event.emitting_node = notifier
                await self.server.iserver.subscription_service.trigger_event(event)
        if rows:
            await self.history.save_bin_events(rows)

    async def run(self) -> None:
        """Serve until ``stop()``; advance in real time unless in lockstep."""
        tick = float(self.config["server"]["tick_s"])
        last = time.monotonic()
        while not self._stop.is_set():
            try:
                await asyncio.wait_for(self._stop.wait(), tick)
            except TimeoutError:
                pass
            now = time.monotonic()
            if not (self.lockstep or self.paused):
                # bounded work per tick: after a stall the clock catches up at most
                # MAX_CATCH_UP_S of wall time per tick (else one huge step makes the
                # next tick later still, and the loop never recovers)
                wall = now - last
                if wall > MAX_CATCH_UP_S and now - self._slow_warned_at > 10.0:
                    self._slow_warned_at = now
                    print(f"serve-800xa: not keeping speed x{self.speed:g}: a tick took "
                          f"{wall:.2f} s of wall time; the clock falls behind", file=sys.stderr,
                          flush=True)
                await self.advance(min(wall, MAX_CATCH_UP_S) * self.speed)
            last = now

    def stop(self) -> None:
        self._stop.set()

    def pause(self) -> None:
        """Freeze the clock (SIGUSR1), so a run can be drained and audited."""
        self.paused = True

    async def shutdown(self) -> None:
        await self.store.save_async(self.process, force=True)
        self.store.close()
        await self.server.stop()

    def ledger(self) -> dict:
        out = self.process.ledger()
        out.update({"paused": self.paused, "max_surrogate_lag_s": self.max_surrogate_lag_s,
                    "surrogate_time_s": self.surrogate_time,
                    "refusals": self.refusals.count, "refusals_by_status": self.refusals.by_status,
                    "speed": self.speed, "lockstep": self.lockstep})
        return out

    # --------------------------------------------------------------- methods
    def _method(self, spec: tuple, body):
        """A method callback: argument count and types checked against ``spec``
        (``(name, VariantType, is_array)`` per input argument) before ``body``
        gets the plain values; a refusal names the argument and marks it in
        ``InputArgumentResults``."""
        names = [name for name, _, _ in spec]

        async def call(parent, *args):
            try:
                if len(args) != len(spec):
                    status = "BadArgumentsMissing" if len(args) < len(spec) else "BadTooManyArguments"
                    raise ExchangeRefused(status, "arguments", f"{len(spec)} ({', '.join(names)})",
                                          f"got {len(args)}")
                results = [ua.StatusCode()] * len(args)
                values, bad = [], []
                for k, ((name, vtype, array), variant) in enumerate(zip(spec, args)):
                    value = variant.Value if isinstance(variant, ua.Variant) else None
                    if array and value is None and getattr(variant, "VariantType", None) == vtype:
                        value = []  # an empty array arrives as a null value
                    if not isinstance(variant, ua.Variant) or variant.VariantType != vtype or \
                            isinstance(value, list) != array:
                        got = (variant.VariantType.name + ("[]" if isinstance(value, list) else "")
                               if isinstance(variant, ua.Variant) else type(variant).__name__)
                        bad.append(f"{name}: must be {vtype.name}{'[]' if array else ''} (got {got})")
                        results[k] = ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
                    values.append(value)
                if bad:
                    return await self._refused_call(
                        ExchangeRefused("BadTypeMismatch", "arguments", "; ".join(bad)), results)
                message, vtype = await body(*values)
            except ExchangeRefused as exc:
                results = [ua.StatusCode()] * len(args)
                if exc.field in names and len(args) == len(spec):
                    results[names.index(exc.field)] = ua.StatusCode(getattr(ua.StatusCodes,
                                                                            exc.status))
                return await self._refused_call(exc, results if len(args) == len(spec) else [])
            return [ua.Variant(message, vtype)]

        return call

    async def _refused_call(self, exc: ExchangeRefused, input_results=()) -> ua.CallMethodResult:
        await self.refuse(exc.status, exc.message)
        result = ua.CallMethodResult()
        result.StatusCode = ua.StatusCode(getattr(ua.StatusCodes, exc.status))
        result.InputArgumentResults = list(input_results)
        result.OutputArguments = [ua.Variant(exc.message, ua.VariantType.String)]
        return result

    async def _acknowledge(self, sequence: int):
        async with self._lock:
            acked = self.process.acknowledge(sequence)
            await self.store.save_async(self.process)
            await self._publish_inbound()
        return f"acknowledged up to {acked}", ua.VariantType.String

    async def _report(self, sequence: int, tracking_ids: list, masses: list, grades: list):
        if len(tracking_ids) > MAX_REPORT_ROWS:  # before any work on the arrays
            raise ExchangeRefused("BadTooManyOperations", "tracking_ids",
                                  f"at most {MAX_REPORT_ROWS} per report", f"got {len(tracking_ids)}")
        async with self._lock:
            message = self.process.report_outflow(sequence, np.array(tracking_ids, dtype=np.uint64),
                                                  np.array(masses, dtype=float),
                                                  np.array(grades, dtype=float))
            await self.store.save_async(self.process)
            await self.publish()
        return message, ua.VariantType.String

    async def _advance_time(self, seconds: float):
        if not self.lockstep:
            raise ExchangeRefused("BadInvalidState", "AdvanceTime",
                                  "called only on a server started with --lockstep")
        await self.advance(_check("seconds", seconds, 0.0, 3600.0))
        return self.process.time, ua.VariantType.Double


UNITS = {
    "s": ("SEC", "s", "second"), "m": ("MTR", "m", "metre"),
    "m/s": ("MTS", "m/s", "metre per second"), "kg": ("KGM", "kg", "kilogram"),
    "kg/s": ("KGS", "kg/s", "kilogram per second"), "1": ("C62", "1", "one (mass fraction)"),
}
"""EngineeringUnits: UNECE Recommendation 20 common codes (OPC UA Part 8, EUInformation)."""
UNECE_NAMESPACE = "http://www.opcfoundation.org/UA/units/un/cefact"


def _eu_information(unit: str) -> ua.EUInformation:
    code, symbol, name = UNITS[unit]
    info = ua.EUInformation()
    info.NamespaceUri = UNECE_NAMESPACE
    info.UnitId = int.from_bytes(code.encode("ascii"), "big")  # Part 8: the code's octets
    info.DisplayName = ua.LocalizedText(symbol)
    info.Description = ua.LocalizedText(name)
    return info


def _now():
    return datetime.now(timezone.utc)


async def _describe(node, text: str) -> None:
    await node.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.LocalizedText(text)))


def _arg(name: str, datatype: int, description: str, array: bool = False) -> ua.Argument:
    arg = ua.Argument()
    arg.Name = name
    arg.DataType = ua.NodeId(datatype)
    arg.ValueRank = 1 if array else -1
    arg.ArrayDimensions = [0] if array else []
    arg.Description = ua.LocalizedText(description)
    return arg


def _check(field_name: str, value, low: float, high: float) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ExchangeRefused("BadTypeMismatch", field_name, "a number",
                              f"got {type(value).__name__}") from None
    if not math.isfinite(number) or number < low or number > high:
        raise ExchangeRefused("BadOutOfRange", field_name, f"finite and in [{low:g}, {high:g}]",
                              f"got {number}")
    return number


def _write_json(path: Path, data: dict) -> None:
    tmp = Path(path).with_suffix(".tmp")
    tmp.write_text(json.dumps(data))
    tmp.replace(path)


async def serve(config: dict, *, speed: float = 1.0, insecure: bool = False,
                lockstep: bool = False, ledger_path: Path | None = None,
                ready_file: Path | None = None, until_s: float | None = None) -> int:
    """Run the server until SIGINT/SIGTERM; write the ledger JSON at the end.

    ``until_s``: the clock freezes at that simulation time and the ledger is
    written, as on SIGUSR1."""
    plant = PlantServer(config, speed=speed, insecure=insecure, lockstep=lockstep,
                        until_s=until_s)
    try:
        await plant.start()
    except ListenError as exc:
        print(f"minetwin serve-800xa: error: {exc}", file=sys.stderr)
        return 1
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, plant.stop)

    def pause_and_write_ledger():
        plant.pause()
        if ledger_path:
            _write_json(ledger_path, plant.ledger())
        print(f"serve-800xa: clock paused at {plant.process.time:.3f} s", file=sys.stderr,
              flush=True)

    loop.add_signal_handler(signal.SIGUSR1, pause_and_write_ledger)
    plant.on_until = pause_and_write_ledger
    mode = "lockstep" if lockstep else f"speed x{speed:g}"
    print(f"serve-800xa: listening on {plant.endpoint} ({mode})", file=sys.stderr, flush=True)
    if ready_file:
        Path(ready_file).write_text(plant.endpoint)
    try:
        await plant.run()
    finally:
        if ledger_path:
            _write_json(ledger_path, plant.ledger())
        await plant.shutdown()
    print("serve-800xa: stopped", file=sys.stderr)
    return 0
