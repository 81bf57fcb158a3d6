"""Security defects of issue 18, each exercised as an outside OPC UA client would.

A real ``minetwin serve-800xa`` process (127.0.0.1, free port) and asyncua
clients over Basic256Sha256 SignAndEncrypt, going around asyncua's own
client-side checks where an attacker would (a second session on one channel,
a forged authentication token, a None channel, wrongly typed arguments).
The node-opcua client of ``test_opcua_interop.py`` repeats the checks with
an implementation nobody here wrote.
"""

import asyncio
import subprocess
import sys
import time

import pytest
from asyncua import ua

from minetwin.harness import ServerProcess, connect, prepare_state
from opcua_server.process import MAX_REPORT_ROWS
from opcua_protocol import APPLICATION_URI_CLIENT
from opcua_server.security import ensure_certificate, pki_paths, trust_certificate

NS = "urn:minetwin:mock800xa"
S = ua.StatusCodes


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    root = tmp_path_factory.mktemp("opcua_security")
    state = prepare_state(root / "state")
    server = ServerProcess(root, state, lockstep=True)
    try:
        asyncio.run(_as(server, state, "surrogate", lambda c, n: n["plant"].call_method(
            n["advance"], ua.Variant(60.0, ua.VariantType.Double))))
        yield server, state
    finally:
        server.stop()


async def _nodes(client):
    idx = await client.get_namespace_index(NS)
    return {name: client.get_node(ua.NodeId(ident, idx)) for name, ident in {
        "plant": "Plant", "advance": "Plant.AdvanceTime", "time": "Plant.SimulationTime",
        "setpoint": "Plant.SP201.DischargeRateSetpoint", "held": "Plant.SP201.HeldMass",
        "sp201": "Plant.SP201", "ack": "Plant.SP201.Inbound.Acknowledge",
        "pending_ids": "Plant.SP201.Inbound.PendingTrackingIds",
        "pending_masses": "Plant.SP201.Inbound.PendingMasses",
        "outbound": "Plant.SP201.Outbound", "report": "Plant.SP201.Outbound.ReportOutflow",
        "out_seq": "Plant.SP201.Outbound.LastSequence", "refusal": "Plant.SP201.LastRefusal",
        "belt_speed": "Plant.CV101.BeltSpeed"}.items()}


async def _as(server, state, role, body):
    client = await connect(server.url, state, role)
    try:
        return await body(client, await _nodes(client))
    finally:
        await client.disconnect()


def run_as(plant, role):
    server, state = plant
    return lambda body: asyncio.run(_as(server, state, role, body))


def _write_status(node, variant):
    async def go():
        try:
            await node.write_value(ua.DataValue(variant))
            return "Good"
        except ua.UaStatusCodeError as exc:
            return type(exc).__name__
    return go()


async def _call(client, n, method, *args):
    request = ua.CallMethodRequest()
    request.ObjectId = n["outbound" if method == "report" else "sp201"].nodeid
    request.MethodId = n[method].nodeid
    request.InputArguments = list(args)
    return (await client.uaclient.call([request]))[0]


# ----------------------------------------------------------- 1. identity
def test_a_second_session_on_one_channel_is_refused_and_the_first_keeps_its_identity(plant):
    async def body(client, n):
        with pytest.raises(ua.UaStatusCodeError) as second:
            await client.create_session()
        # the viewer's session is still the viewer's: its write is refused
        status = await _write_status(n["setpoint"], ua.Variant(1234.0, ua.VariantType.Double))
        return second.value.code, status, await n["setpoint"].read_value()

    code, status, setpoint = run_as(plant, "viewer")(body)
    assert code == S.BadTooManySessions
    assert status == "BadUserAccessDenied" and setpoint != 1234.0


def test_a_request_with_another_authentication_token_is_refused(plant):
    async def body(client, n):
        session = client.uaclient.protocol  # it stamps every request header
        own = session.authentication_token
        session.authentication_token = ua.NodeId(own.Identifier + 1, own.NamespaceIndex)
        try:
            with pytest.raises(ua.UaStatusCodeError) as forged:
                await n["time"].read_value()
        finally:
            session.authentication_token = own
        await n["time"].read_value()  # the real token still works
        return forged.value.code

    assert run_as(plant, "operator")(body) == S.BadSessionIdInvalid


# ------------------------------------------------- 2. the None channel
def test_the_none_channel_serves_discovery_but_no_session(plant):
    from asyncua import Client

    server, state = plant

    async def body():
        client = Client(server.url, timeout=4)
        await client.connect_socket()
        try:
            await client.send_hello()
            await client.open_secure_channel()
            endpoints = await client.get_endpoints()  # discovery still works
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await client.create_session()
            return len(endpoints), refused.value.code
        finally:
            client.disconnect_socket()

    count, code = asyncio.run(body())
    assert count == 3 and code == S.BadSecurityModeRejected


FLOOD_CLIENT = """
import asyncio, sys, time
from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
url, cert, key, attempts = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
async def main():
    codes = []
    for _ in range(attempts):
        client = Client(url, timeout=10)
        client.application_uri = "urn:minetwin:stockpile:client"
        client.set_user("operator")
        client.set_password("wrong-password")
        await client.set_security(SecurityPolicyBasic256Sha256, cert, key,
                                  mode=ua.MessageSecurityMode.SignAndEncrypt)
        try:
            await client.connect()
            codes.append("Good")
            await client.disconnect()
        except ua.UaStatusCodeError as exc:
            codes.append(type(exc).__name__)
    print(" ".join(codes))
asyncio.run(main())
"""


@pytest.mark.slow
def test_a_failed_login_flood_neither_stalls_the_plant_clock_nor_locks_out_other_clients(tmp_path):
    """4 client processes, 10 wrong passwords each, with their own trusted
    certificate; the plant runs at speed 4 with a 0.05 s tick.

    Before the fix each check ran scrypt (~150 ms) in the event loop: 20 wrong
    attempts froze the clock 1.7 s. Now hashing runs in one worker thread and
    the client is throttled after 3 failures, so over every 5 s of wall time
    SimulationTime advances speed x wall within 5 %, and reads of it are served
    promptly (95 % of round trips < 0.15 s). Measured on 2 shared cores: with
    scrypt in the loop and no throttle, windows of 0.92-1.07 and round trips
    up to 0.34 s (p95 ~0.29 s); with the fix 0.98-1.02 and at most 0.03 s.
    """
    state = prepare_state(tmp_path / "state")
    pki = pki_paths(tmp_path / "attacker")
    asyncio.run(ensure_certificate(pki["key"], pki["cert"], APPLICATION_URI_CLIENT, True))
    attacker_cert = pki["cert"].with_name("attacker.der")  # not over the run's client cert
    pki["cert"].rename(attacker_cert)
    trust_certificate(state["server_state"], attacker_cert)
    speed = 4.0
    server = ServerProcess(tmp_path, state, speed=speed)
    try:
        async def sample():
            client = await connect(server.url, state, "viewer")
            try:
                n = await _nodes(client)
                flood = [await asyncio.create_subprocess_exec(
                    sys.executable, "-c", FLOOD_CLIENT, server.url, str(attacker_cert),
                    str(pki["key"]), "10", stdout=asyncio.subprocess.PIPE) for _ in range(4)]
                samples, round_trips = [], []
                waiter = asyncio.gather(*(p.communicate() for p in flood))
                legit = None
                while not waiter.done() or len(samples) < 50:
                    asked = time.monotonic()
                    value = await n["time"].read_value()
                    samples.append((time.monotonic(), value))
                    round_trips.append(samples[-1][0] - asked)
                    if legit is None and len(samples) == 20:  # mid-flood, the real certificate
                        legit = await _as(server, state, "operator",
                                          lambda c, m: m["setpoint"].read_value())
                    await asyncio.sleep(0.1)
                return (samples, round_trips, [out.decode().split() for out, _ in await waiter],
                        legit)
            finally:
                await client.disconnect()

        samples, round_trips, codes, legit = asyncio.run(sample())
    finally:
        server.stop()
    ratios = []
    for i, (wall0, sim0) in enumerate(samples):
        later = [(w, s) for w, s in samples[i:] if w - wall0 >= 5.0]
        if later:
            wall1, sim1 = later[0]
            ratios.append((sim1 - sim0) / (speed * (wall1 - wall0)))
    assert sorted(round_trips)[int(0.95 * len(round_trips))] < 0.15, sorted(round_trips)[-10:]
    assert ratios and min(ratios) >= 0.95 and max(ratios) <= 1.05, (min(ratios), max(ratios))
    assert all(c == ["BadUserAccessDenied"] * 10 for c in codes), codes
    assert legit is not None  # the operator with the trusted client certificate got in
    assert "failed logins, next check in" in server.log_path.read_text()  # throttled


# ------------------------------------------------ 3. subscription owner
def test_a_viewer_cannot_delete_or_modify_the_operators_subscription(plant):
    server, state = plant

    class Handler:
        changes = 0

        def datachange_notification(self, node, value, data):
            Handler.changes += 1

    async def body():
        operator = await connect(server.url, state, "operator")
        viewer = await connect(server.url, state, "viewer")
        try:
            n = await _nodes(operator)
            subscription = await operator.create_subscription(50, Handler())
            await subscription.subscribe_data_change(n["setpoint"])
            deleted = await viewer.uaclient.delete_subscriptions([subscription.subscription_id])
            params = ua.ModifySubscriptionParameters()
            params.SubscriptionId = subscription.subscription_id
            params.RequestedPublishingInterval = 10000
            with pytest.raises(ua.UaStatusCodeError) as modified:
                await viewer.uaclient.update_subscription(params)
            await asyncio.sleep(0.3)
            before = Handler.changes
            await n["setpoint"].write_value(ua.DataValue(ua.Variant(222.0, ua.VariantType.Double)))
            await asyncio.sleep(0.5)
            own = await operator.uaclient.delete_subscriptions([subscription.subscription_id])
            return deleted, modified.value.code, Handler.changes - before, own
        finally:
            await viewer.disconnect()
            await operator.disconnect()

    deleted, modified, changes, own = asyncio.run(body())
    assert [s.value for s in deleted] == [S.BadSubscriptionIdInvalid]
    assert modified == S.BadSubscriptionIdInvalid
    assert changes >= 1  # the operator still receives its notifications
    assert [s.value for s in own] == [S.Good]


def test_a_viewer_cannot_condition_refresh_the_operators_subscription(plant):
    """Part 9, 5.5.7: the server verifies the subscription is the calling session's
    (Bad_UserAccessDenied otherwise); asyncua alone queued the refresh events in
    the operator's subscription."""
    server, state = plant
    refresh_start = ua.NodeId(ua.ObjectIds.RefreshStartEventType)

    class Events:
        refreshes = 0

        def event_notification(self, event):
            Events.refreshes += event.EventType == refresh_start

    async def refresh(client, subscription_id):
        request = ua.CallMethodRequest()
        request.ObjectId = ua.NodeId(ua.ObjectIds.ConditionType)
        request.MethodId = ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh)
        request.InputArguments = [ua.Variant(subscription_id, ua.VariantType.UInt32)]
        return (await client.uaclient.call([request]))[0].StatusCode.value

    async def body():
        operator = await connect(server.url, state, "operator")
        viewer = await connect(server.url, state, "viewer")
        try:
            subscription = await operator.create_subscription(50, Events())
            await subscription.subscribe_events(operator.nodes.server, queuesize=100)
            own_viewer = await viewer.create_subscription(50, Events())
            foreign = await refresh(viewer, subscription.subscription_id)
            await asyncio.sleep(0.5)
            after_foreign = Events.refreshes
            mine = await refresh(viewer, own_viewer.subscription_id)
            operators = await refresh(operator, subscription.subscription_id)
            await asyncio.sleep(0.5)
            return foreign, after_foreign, mine, operators, Events.refreshes
        finally:
            await viewer.disconnect()
            await operator.disconnect()

    foreign, after_foreign, mine, operators, refreshes = asyncio.run(body())
    assert foreign == S.BadUserAccessDenied
    assert after_foreign == 0  # nothing reached the operator's subscription
    assert mine == S.Good and operators == S.Good
    assert refreshes == 1  # the operator's own refresh did arrive: the count can see them


# ------------------------------------------------------ 4. type checks
def test_wrongly_typed_writes_are_refused_with_bad_type_mismatch(plant):
    async def body(client, n):
        before = await n["setpoint"].read_value()
        statuses = [await _write_status(n["setpoint"], v) for v in (
            ua.Variant("150", ua.VariantType.String), ua.Variant(True, ua.VariantType.Boolean),
            ua.Variant(100, ua.VariantType.Int32), ua.Variant([1.0], ua.VariantType.Double))]
        return statuses, before, await n["setpoint"].read_value(), await n["refusal"].read_value()

    statuses, before, after, refusal = run_as(plant, "operator")(body)
    assert statuses == ["BadTypeMismatch"] * 4
    assert after == before
    assert "must be a scalar Double" in refusal and "np." not in refusal


def test_wrongly_typed_method_arguments_are_refused_per_argument(plant):
    async def body(client, n):
        ids = await n["pending_ids"].read_value()
        result = await _call(client, n, "report", ua.Variant(1, ua.VariantType.UInt64),
                             ua.Variant([float(ids[0]) + 0.7], ua.VariantType.Double),
                             ua.Variant(["1.0"], ua.VariantType.String),
                             ua.Variant([True], ua.VariantType.Boolean))
        ack = await _call(client, n, "ack", ua.Variant(1.0, ua.VariantType.Double))
        return result, ack, await n["out_seq"].read_value()

    result, ack, out_seq = run_as(plant, "surrogate")(body)
    assert result.StatusCode.value == S.BadTypeMismatch
    assert [s.value for s in result.InputArgumentResults] == [
        S.Good, S.BadTypeMismatch, S.BadTypeMismatch, S.BadTypeMismatch]
    assert "tracking_ids: must be UInt64[] (got Double[])" in result.OutputArguments[0].Value
    assert ack.StatusCode.value == S.BadTypeMismatch
    assert [s.value for s in ack.InputArgumentResults] == [S.BadTypeMismatch]
    assert out_seq == 0  # nothing applied


# ------------------------------------------------- 5. replayed sequence
def test_a_replayed_outflow_number_with_other_contents_is_a_refused_conflict(plant):
    def report(seq, tid, mass):
        return (ua.Variant(seq, ua.VariantType.UInt64), ua.Variant([tid], ua.VariantType.UInt64),
                ua.Variant([mass], ua.VariantType.Double), ua.Variant([0.01], ua.VariantType.Double))

    async def body(client, n):
        tid = int((await n["pending_ids"].read_value())[1])
        first = await _call(client, n, "report", *report(1, tid, 5.0))
        again = await _call(client, n, "report", *report(1, tid, 5.0))
        conflict = await _call(client, n, "report", *report(1, tid, 6.0))
        zero = await _call(client, n, "report", *report(0, tid, 1.0))
        return first, again, conflict, zero, await n["out_seq"].read_value()

    first, again, conflict, zero, out_seq = run_as(plant, "surrogate")(body)
    assert first.StatusCode.is_good() and first.OutputArguments[0].Value == "applied"
    assert again.StatusCode.is_good() and again.OutputArguments[0].Value == "already applied"
    assert conflict.StatusCode.value == S.BadSequenceNumberInvalid
    assert "report 1 was applied with other contents" in conflict.OutputArguments[0].Value
    assert [s.value for s in conflict.InputArgumentResults][0] == S.BadSequenceNumberInvalid
    assert zero.StatusCode.value == S.BadSequenceNumberInvalid
    assert out_seq == 1
    assert "refused: BadSequenceNumberInvalid: sequence" in plant[0].log_path.read_text()


# -------------------------------------------------- 6. argument counts
def test_wrong_argument_counts_get_their_status_and_no_traceback(plant):
    async def body(client, n):
        one = ua.Variant(1, ua.VariantType.UInt64)
        missing = await _call(client, n, "report", one, ua.Variant([1], ua.VariantType.UInt64))
        extra = await _call(client, n, "ack", one, one)
        next_report = await n["out_seq"].read_value() + 1
        out_of_range = await _call(client, n, "report",
                                   ua.Variant(next_report, ua.VariantType.UInt64),
                                   ua.Variant([1], ua.VariantType.UInt64),
                                   ua.Variant([-1.0], ua.VariantType.Double),
                                   ua.Variant([0.01], ua.VariantType.Double))
        return missing, extra, out_of_range

    missing, extra, out_of_range = run_as(plant, "surrogate")(body)
    assert missing.StatusCode.value == S.BadArgumentsMissing
    assert "arguments: must be 4 (sequence, tracking_ids, masses, grades) (got 2)" in \
        missing.OutputArguments[0].Value
    assert extra.StatusCode.value == S.BadTooManyArguments
    assert out_of_range.StatusCode.value == S.BadOutOfRange
    assert [s.value for s in out_of_range.InputArgumentResults] == [
        S.Good, S.Good, S.BadOutOfRange, S.Good]
    assert out_of_range.OutputArguments[0].Value == \
        "masses: must be finite and > 0 kg (got -1.0 at index 0)"
    assert "Traceback" not in plant[0].log_path.read_text()


# -------------------------------------------------- 7. access attributes
def test_user_access_level_and_user_executable_follow_the_role(plant):
    def attributes(client, n):
        async def go():
            nodes = [n["setpoint"], n["held"], n["belt_speed"], n["time"]]
            levels = [await node.read_attribute(ua.AttributeIds.UserAccessLevel) for node in nodes]
            executable = [await n[m].read_attribute(ua.AttributeIds.UserExecutable)
                          for m in ("report", "ack", "advance")]
            # CurrentRead | CurrentWrite bits (HistoryRead is set where history is kept)
            return [v.Value.Value & 3 for v in levels], [v.Value.Value for v in executable]
        return go()

    read, write = 1, 3  # CurrentRead, CurrentRead | CurrentWrite
    assert run_as(plant, "viewer")(attributes) == ([read] * 4, [False] * 3)
    assert run_as(plant, "operator")(attributes) == ([write, read, write, read], [False] * 3)
    assert run_as(plant, "surrogate")(attributes) == ([read, write, read, read], [True] * 3)


# ---------------------------------------------------------- 8. arrays
def test_an_outflow_report_longer_than_the_bound_is_refused_at_once(plant):
    async def body(client, n):
        rows = MAX_REPORT_ROWS + 1
        started = time.monotonic()
        result = await _call(client, n, "report", ua.Variant(2, ua.VariantType.UInt64),
                             ua.Variant(list(range(1, rows + 1)), ua.VariantType.UInt64),
                             ua.Variant([1.0] * rows, ua.VariantType.Double),
                             ua.Variant([0.01] * rows, ua.VariantType.Double))
        return result, time.monotonic() - started

    result, elapsed = run_as(plant, "surrogate")(body)
    assert result.StatusCode.value == S.BadTooManyOperations
    assert f"tracking_ids: must be at most {MAX_REPORT_ROWS} per report" in \
        result.OutputArguments[0].Value
    assert elapsed < 5.0


def _alt_names(cert_file):
    from cryptography import x509

    cert = x509.load_der_x509_certificate(cert_file.read_bytes())
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    return (set(names.get_values_for_type(x509.DNSName)),
            {str(ip) for ip in names.get_values_for_type(x509.IPAddress)})


def test_a_server_certificate_names_every_host_it_is_reached_by_and_follows_a_moved_host(tmp_path):
    import socket

    from opcua_protocol import APPLICATION_URI_SERVER

    pki = pki_paths(tmp_path / "server")
    assert asyncio.run(ensure_certificate(pki["key"], pki["cert"], APPLICATION_URI_SERVER, False))
    dns, ips = _alt_names(pki["cert"])
    assert dns == {"localhost", socket.gethostname()} and ips == {"127.0.0.1"}
    key = pki["key"].read_bytes()
    assert not asyncio.run(ensure_certificate(pki["key"], pki["cert"], APPLICATION_URI_SERVER,
                                              False))  # nothing missing: kept

    assert asyncio.run(ensure_certificate(pki["key"], pki["cert"], APPLICATION_URI_SERVER, False,
                                          endpoint_host="plant-gateway.example"))
    dns, ips = _alt_names(pki["cert"])
    assert "plant-gateway.example" in dns and ips == {"127.0.0.1"}
    assert pki["key"].read_bytes() == key  # a new certificate of the same key

    assert asyncio.run(ensure_certificate(pki["key"], pki["cert"], APPLICATION_URI_SERVER, False,
                                          endpoint_host="10.1.2.3"))
    assert _alt_names(pki["cert"])[1] == {"127.0.0.1", "10.1.2.3"}
    assert not asyncio.run(ensure_certificate(pki["key"], pki["cert"], APPLICATION_URI_SERVER,
                                              False, endpoint_host="0.0.0.0"))  # a wildcard: no name
