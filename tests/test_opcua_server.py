"""The real OPC UA server process: security, roles, bad input over the wire.

One lockstep server (a real ``minetwin serve-800xa`` process on 127.0.0.1 and
a free port) serves the module; the clock only moves when a test calls
``Plant.AdvanceTime`` as the surrogate, so the state each test sees is known.
"""

import asyncio
import math

import pytest
from asyncua import ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

from minetwin.harness import ServerProcess, connect, prepare_state
from opcua_protocol import APPLICATION_URI_CLIENT
from opcua_server.security import ensure_certificate, pki_paths

NS = "urn:minetwin:mock800xa"


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    root = tmp_path_factory.mktemp("opcua_server")
    state = prepare_state(root / "state")
    server = ServerProcess(root, state, lockstep=True)
    try:
        asyncio.run(_advance(server.url, state, 60.0))  # bins have reached the stockpile
        yield server, state
    finally:
        server.stop()


async def _advance(url, state, seconds):
    client = await connect(url, state, "surrogate")
    try:
        nodes = await _nodes(client)
        await nodes["plant"].call_method(nodes["advance"], ua.Variant(seconds, ua.VariantType.Double))
    finally:
        await client.disconnect()


async def _nodes(client):
    idx = await client.get_namespace_index(NS)
    node = lambda name: client.get_node(ua.NodeId(name, idx))  # noqa: E731
    return {"plant": node("Plant"), "advance": node("Plant.AdvanceTime"),
            "setpoint": node("Plant.SP201.DischargeRateSetpoint"),
            "sp201": node("Plant.SP201"), "held": node("Plant.SP201.HeldMass"),
            "inbound": node("Plant.SP201.Inbound"),
            "ack": node("Plant.SP201.Inbound.Acknowledge"),
            "acked": node("Plant.SP201.Inbound.AcknowledgedSequence"),
            "last": node("Plant.SP201.Inbound.LastSequence"),
            "pending_ids": node("Plant.SP201.Inbound.PendingTrackingIds"),
            "pending_masses": node("Plant.SP201.Inbound.PendingMasses"),
            "outbound": node("Plant.SP201.Outbound"),
            "report": node("Plant.SP201.Outbound.ReportOutflow"),
            "out_seq": node("Plant.SP201.Outbound.LastSequence"),
            "refusal": node("Plant.SP201.LastRefusal"),
            "belt_ids": node("Plant.CV101.BinTrackingIds"),
            "cv301_mass": node("Plant.CV301.Mass")}


def session(plant, role, **kwargs):
    server, state = plant

    def decorator(body):
        async def runner():
            client = await connect(server.url, state, role, **kwargs)
            try:
                return await body(client, await _nodes(client))
            finally:
                await client.disconnect()
        return asyncio.run(runner())
    return decorator


# ------------------------------------------------------------------ security
def test_only_sign_and_encrypt_endpoints_by_default(plant):
    from asyncua import Client

    async def body():
        client = Client(plant[0].url)
        endpoints = await client.connect_and_get_server_endpoints()
        return {(e.SecurityPolicyUri.split("#")[-1], e.SecurityMode) for e in endpoints}, \
            {t.TokenType for e in endpoints for t in e.UserIdentityTokens}

    policies, tokens = asyncio.run(body())
    assert {p for p, _ in policies} == {"Basic256Sha256", "Aes128_Sha256_RsaOaep",
                                        "Aes256_Sha256_RsaPss"}
    assert {m for _, m in policies} == {ua.MessageSecurityMode.SignAndEncrypt}
    assert tokens == {ua.UserTokenType.UserName}  # no anonymous token offered


@pytest.mark.parametrize("attempt", ["anonymous", "wrong_password", "admin_user", "no_security",
                                     "untrusted_certificate"])
def test_refused_sessions(plant, attempt, tmp_path):
    server, state = plant
    kwargs = {}
    role = "viewer"
    if attempt == "anonymous":
        role = None
    elif attempt == "wrong_password":
        kwargs["password"] = "not-the-password"
    elif attempt == "no_security":
        kwargs["secure"] = False
    elif attempt == "untrusted_certificate":
        pki = pki_paths(tmp_path)
        asyncio.run(ensure_certificate(pki["key"], pki["cert"], APPLICATION_URI_CLIENT, True))
        kwargs.update(certificate=pki["cert"], private_key=pki["key"])

    async def body():
        if attempt == "admin_user":  # asyncua's default manager would make this an Admin
            from asyncua import Client
            client = Client(server.url, timeout=4)
            client.application_uri = APPLICATION_URI_CLIENT
            client.set_user("admin")
            client.set_password("admin")
            await client.set_security(SecurityPolicyBasic256Sha256, str(state["client_cert"]),
                                      str(state["client_key"]),
                                      mode=ua.MessageSecurityMode.SignAndEncrypt)
            await client.connect()
            return client
        return await connect(server.url, state, role, **kwargs)

    if attempt != "no_security":
        async def attempt_session():
            client = await body()
            await client.disconnect()
    else:
        # asyncua's client itself refuses (no None endpoint offered), so go
        # around it: a None channel, then a session on it (the server refuses
        # it before any password is seen: that channel is no password oracle)
        async def attempt_session():
            from asyncua import Client
            client = Client(server.url, timeout=4)
            await client.connect_socket()
            try:
                await client.send_hello()
                await client.open_secure_channel()
                await client.create_session()
            finally:
                client.disconnect_socket()

    expected = {"anonymous": ua.StatusCodes.BadIdentityTokenRejected,
                "wrong_password": ua.StatusCodes.BadUserAccessDenied,
                "admin_user": ua.StatusCodes.BadUserAccessDenied,
                "no_security": ua.StatusCodes.BadSecurityModeRejected,
                "untrusted_certificate": ua.StatusCodes.BadCertificateUntrusted}[attempt]
    with pytest.raises(ua.UaStatusCodeError) as err:
        asyncio.run(attempt_session())
    assert err.value.code == expected


def test_viewer_reads_but_may_not_write_or_call(plant):
    @session(plant, "viewer")
    async def result(client, n):
        before = await n["setpoint"].read_value()
        ids = await n["belt_ids"].read_value()
        denied = []
        for action in (lambda: n["setpoint"].write_value(ua.Variant(100.0, ua.VariantType.Double)),
                       lambda: n["sp201"].call_method(n["ack"], ua.Variant(0, ua.VariantType.UInt64)),
                       lambda: n["plant"].add_object(ua.NodeId("X", 2), "X")):
            try:
                await action()
            except ua.UaStatusCodeError as exc:
                denied.append(exc.code)
        return before, ids, denied, await n["setpoint"].read_value()

    before, ids, denied, after = result
    assert len(ids) == 20
    assert denied == [ua.StatusCodes.BadUserAccessDenied] * 3
    assert after == before


def test_operator_writes_setpoint_in_range_only(plant):
    @session(plant, "operator")
    async def result(client, n):
        await n["setpoint"].write_value(ua.Variant(500.0, ua.VariantType.Double))
        accepted = await n["setpoint"].read_value()
        codes = []
        for bad in (-1.0, 2000.5, float("nan"), float("inf")):
            try:
                await n["setpoint"].write_value(ua.Variant(bad, ua.VariantType.Double))
            except ua.UaStatusCodeError as exc:
                codes.append(exc.code)
        refusal = await n["refusal"].read_value()
        try:  # an operator may not report outflow
            await n["outbound"].call_method(n["report"], ua.Variant(1, ua.VariantType.UInt64),
                                            ua.Variant([1], ua.VariantType.UInt64),
                                            ua.Variant([1.0], ua.VariantType.Double),
                                            ua.Variant([0.1], ua.VariantType.Double))
            report_code = None
        except ua.UaStatusCodeError as exc:
            report_code = exc.code
        final = await n["setpoint"].read_value()
        await n["setpoint"].write_value(ua.Variant(240.0, ua.VariantType.Double))
        return accepted, codes, refusal, report_code, final

    accepted, codes, refusal, report_code, final = result
    assert accepted == 500.0 and final == 500.0
    assert codes == [ua.StatusCodes.BadOutOfRange] * 4
    assert refusal.startswith("BadOutOfRange: DischargeRateSetpoint: must be in [0, 2000] kg/s")
    assert report_code == ua.StatusCodes.BadUserAccessDenied


def test_surrogate_writes_its_reports_in_range_but_not_the_setpoint(plant):
    @session(plant, "surrogate")
    async def codes(client, n):
        idx = await client.get_namespace_index(NS)
        grade = client.get_node(ua.NodeId("Plant.SP201.AverageGrade", idx))
        out = []
        for node, value in ((n["setpoint"], 100.0), (n["held"], -1.0), (n["held"], math.nan),
                            (grade, 1.5)):
            try:
                await node.write_value(ua.Variant(value, ua.VariantType.Double))
                out.append(None)
            except ua.UaStatusCodeError as exc:
                out.append(exc.code)
        await n["held"].write_value(ua.Variant(1234.5, ua.VariantType.Double))
        await grade.write_value(ua.Variant(0.02, ua.VariantType.Double))
        return out, await n["held"].read_value(), await grade.read_value()

    refused, held, grade = codes
    assert refused == [ua.StatusCodes.BadUserAccessDenied] + [ua.StatusCodes.BadOutOfRange] * 3
    assert held == 1234.5 and grade == 0.02


async def _raw_call(client, n, *args):
    """CallMethodResult as the server sent it (status and output message)."""
    request = ua.CallMethodRequest()
    request.ObjectId = n["outbound"].nodeid
    request.MethodId = n["report"].nodeid
    request.InputArguments = list(args)
    return (await client.uaclient.call([request]))[0]


BAD_REPORTS = [
    ("negative mass", {"masses": [-5.0]}, "BadOutOfRange", "masses:"),
    ("NaN mass", {"masses": [math.nan]}, "BadOutOfRange", "masses:"),
    ("infinite mass", {"masses": [math.inf]}, "BadOutOfRange", "masses:"),
    ("grade above 1", {"grades": [1.2]}, "BadOutOfRange", "grades:"),
    ("grade below 0", {"grades": [-0.1]}, "BadOutOfRange", "grades:"),
    ("unknown tracking id", {"tracking_ids": [123456789]}, "BadInvalidArgument",
     "tracking_ids:"),
    ("more than entered", {"masses": [1e6]}, "BadOutOfRange", "masses:"),
    ("lengths differ", {"grades": [0.1, 0.2]}, "BadInvalidArgument", "grades:"),
    ("sequence gap", {"sequence": 7}, "BadSequenceNumberInvalid", "sequence:"),
]


def test_bad_reports_refused_with_status_and_field_state_unchanged(plant):
    @session(plant, "surrogate")
    async def results(client, n):
        tid = (await n["pending_ids"].read_value())[0]
        out = []
        for label, change, status, field in BAD_REPORTS:
            report = {"sequence": 1, "tracking_ids": [tid], "masses": [10.0], "grades": [0.01]}
            report.update(change)
            before = (await n["out_seq"].read_value(), await n["cv301_mass"].read_value())
            result = await _raw_call(
                client, n, ua.Variant(report["sequence"], ua.VariantType.UInt64),
                ua.Variant(report["tracking_ids"], ua.VariantType.UInt64),
                ua.Variant(report["masses"], ua.VariantType.Double),
                ua.Variant(report["grades"], ua.VariantType.Double))
            after = (await n["out_seq"].read_value(), await n["cv301_mass"].read_value())
            out.append((label, result.StatusCode.value, result.OutputArguments[0].Value,
                        before == after, status, field))
        # a bad acknowledgement too
        ack = ua.CallMethodRequest()
        ack.ObjectId, ack.MethodId = n["inbound"].nodeid, n["ack"].nodeid
        ack.InputArguments = [ua.Variant(10**9, ua.VariantType.UInt64)]
        acked_before = await n["acked"].read_value()
        ack_result = (await client.uaclient.call([ack]))[0]
        acked_after = await n["acked"].read_value()
        # and after all that, a good report is applied: nothing broke
        good = await n["outbound"].call_method(
            n["report"], ua.Variant(1, ua.VariantType.UInt64), ua.Variant([tid], ua.VariantType.UInt64),
            ua.Variant([10.0], ua.VariantType.Double), ua.Variant([0.01], ua.VariantType.Double))
        again = await n["outbound"].call_method(
            n["report"], ua.Variant(1, ua.VariantType.UInt64), ua.Variant([tid], ua.VariantType.UInt64),
            ua.Variant([10.0], ua.VariantType.Double), ua.Variant([0.01], ua.VariantType.Double))
        return out, ack_result, acked_before, acked_after, good, again, \
            await n["cv301_mass"].read_value()

    out, ack_result, acked_before, acked_after, good, again, cv301_mass = results
    for label, code, message, unchanged, status, field in out:
        assert code == getattr(ua.StatusCodes, status), label
        assert message.startswith(field), (label, message)
        assert unchanged, label
    assert ack_result.StatusCode.value == ua.StatusCodes.BadOutOfRange
    assert ack_result.OutputArguments[0].Value.startswith("sequence:")
    assert acked_after == acked_before
    assert good == "applied" and again == "already applied"
    assert cv301_mass == pytest.approx(10.0)


def test_discharge_events_carry_the_records(plant):
    server, state = plant

    class Collector:
        def __init__(self):
            self.events = []

        def event_notification(self, event):
            self.events.append((event.Sequence, event.TrackingId, event.Mass))

    async def body():
        client = await connect(server.url, state, "surrogate")
        try:
            n = await _nodes(client)
            idx = await client.get_namespace_index(NS)
            handler = Collector()
            sub = await client.create_subscription(20, handler)
            await sub.subscribe_events(n["sp201"], client.get_node(
                ua.NodeId("BinDischargedEventType", idx)))
            last = await n["last"].read_value()
            await n["plant"].call_method(n["advance"], ua.Variant(10.0, ua.VariantType.Double))
            for _ in range(50):
                if len(handler.events) >= 10:
                    break
                await asyncio.sleep(0.1)
            pending = await n["pending_ids"].read_value()
            return last, handler.events, pending
        finally:
            await client.disconnect()

    last, events, pending = asyncio.run(body())
    assert [e[0] for e in events] == list(range(last + 1, last + 11))  # 1 bin/s for 10 s
    assert all(e[1] in pending for e in events)
    assert all(e[2] == pytest.approx(250.0) for e in events)


@pytest.mark.slow
def test_insecure_mode_says_so_and_still_enforces_users_and_roles(tmp_path):
    state = prepare_state(tmp_path / "state")
    server = ServerProcess(tmp_path, state, insecure=True)
    try:
        async def body():
            viewer = await connect(server.url, state, "viewer", secure=False)
            try:
                n = await _nodes(viewer)
                time_value = await n["plant"].get_child([f"{await viewer.get_namespace_index(NS)}:SimulationTime"])
                read = await time_value.read_value()
                try:
                    await n["setpoint"].write_value(ua.Variant(10.0, ua.VariantType.Double))
                    denied = None
                except ua.UaStatusCodeError as exc:
                    denied = exc.code
            finally:
                await viewer.disconnect()
            try:
                anonymous = await connect(server.url, state, None, secure=False)
                await anonymous.disconnect()
                anonymous_refused = False
            except Exception:
                anonymous_refused = True
            return read, denied, anonymous_refused

        read, denied, anonymous_refused = asyncio.run(body())
    finally:
        server.stop()
    assert read >= 0.0
    assert denied == ua.StatusCodes.BadUserAccessDenied
    assert anonymous_refused
    assert "WARNING: --insecure" in server.log_path.read_text()
