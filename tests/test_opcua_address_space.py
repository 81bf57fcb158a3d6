"""The address space as an integrator's generic client sees it.

``opcua_server/ADDRESS_SPACE.md`` is written by ``python -m
minetwin.address_space`` from a browse of a running server; this test
browses a running server the same way and fails if the file differs (so the
file cannot drift from the server). It also reads what a generic client
shows: timestamps on live values, units and ranges (AnalogItemType with
EngineeringUnits and EURange), array dimensions, and the server
certificate's subjectAltName.
"""

import asyncio
import ipaddress
import socket
from datetime import datetime, timedelta, timezone

import pytest
from asyncua import ua

from minetwin.address_space import DEFAULT_OUT, browse, render
from minetwin.harness import ServerProcess, connect, prepare_state

NS = "urn:minetwin:mock800xa"


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    root = tmp_path_factory.mktemp("address_space")
    state = prepare_state(root / "state")
    server = ServerProcess(root, state, lockstep=True)
    try:
        yield server, state
    finally:
        server.stop()


def _run(plant, role, body):
    server, state = plant

    async def go():
        client = await connect(server.url, state, role)
        try:
            idx = await client.get_namespace_index(NS)
            return await body(client, lambda name: client.get_node(ua.NodeId(name, idx)))
        finally:
            await client.disconnect()
    return asyncio.run(go())


def test_address_space_md_is_what_the_running_server_shows(plant):
    text = _run(plant, "viewer", lambda client, node: browse(client))
    assert render(text) == DEFAULT_OUT.read_text(), (
        "opcua_server/ADDRESS_SPACE.md is out of date: run python -m minetwin.address_space")


def test_units_ranges_and_array_dimensions_are_advertised(plant):
    async def body(client, node):
        out = {}
        for name in ("Plant.CV101.BeltSpeed", "Plant.SP201.DischargeRateSetpoint",
                     "Plant.CV101.BinMasses"):
            props = {(await p.read_browse_name()).Name: await p.read_value()
                     for p in await node(name).get_properties()}
            dims = (await node(name).read_attribute(ua.AttributeIds.ArrayDimensions)).Value.Value
            type_def = await node(name).read_type_definition()
            out[name] = (props, dims, (await client.get_node(type_def).read_browse_name()).Name)
        return out

    found = _run(plant, "viewer", body)
    props, _, type_name = found["Plant.CV101.BeltSpeed"]
    assert type_name == "AnalogItemType"
    assert (props["EURange"].Low, props["EURange"].High) == (0.0, 10.0)
    assert props["EngineeringUnits"].DisplayName.Text == "m/s"
    assert props["EngineeringUnits"].UnitId == int.from_bytes(b"MTS", "big")  # UNECE code
    props, _, _ = found["Plant.SP201.DischargeRateSetpoint"]
    assert (props["EURange"].High, props["EngineeringUnits"].DisplayName.Text) == (2000.0, "kg/s")
    props, dims, type_name = found["Plant.CV101.BinMasses"]
    assert dims == [20] and type_name == "AnalogUnitType"
    assert props["EngineeringUnits"].DisplayName.Text == "kg"


def test_live_values_carry_source_and_server_timestamps(plant):
    async def body(client, node):
        await node("Plant.SP201.DischargeRateSetpoint").write_value(
            ua.DataValue(ua.Variant(250.0, ua.VariantType.Double)))
        params = ua.ReadParameters()
        params.TimestampsToReturn = ua.TimestampsToReturn.Both
        for name in ("Plant.SimulationTime", "Plant.CV101.BinMasses",
                     "Plant.SP201.DischargeRateSetpoint", "Plant.CV301.Mass"):
            item = ua.ReadValueId()
            item.NodeId, item.AttributeId = node(name).nodeid, ua.AttributeIds.Value
            params.NodesToRead.append(item)
        return await client.uaclient.read(params)

    now = datetime.now(timezone.utc)
    for value in _run(plant, "operator", body):
        for stamp in (value.SourceTimestamp, value.ServerTimestamp):
            assert stamp is not None
            stamp = stamp if stamp.tzinfo else stamp.replace(tzinfo=timezone.utc)
            assert abs(stamp - now) < timedelta(minutes=5)


def test_the_server_certificate_names_the_address_its_endpoint_advertises(plant):
    from asyncua import Client
    from cryptography import x509

    async def endpoints():
        return await Client(plant[0].url).connect_and_get_server_endpoints()

    found = asyncio.run(endpoints())
    assert all("127.0.0.1" in e.EndpointUrl for e in found)
    cert = x509.load_der_x509_certificate(found[0].ServerCertificate)
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert ipaddress.ip_address("127.0.0.1") in names.get_values_for_type(x509.IPAddress)
    assert {"localhost", socket.gethostname()} <= set(names.get_values_for_type(x509.DNSName))
    assert "certificate does not contain" not in plant[0].log_path.read_text()
    assert "urn:minetwin:mock800xa:server" in names.get_values_for_type(
        x509.UniformResourceIdentifier)


def test_bin_events_reach_a_generic_client_subscribed_to_the_server_object(plant):
    server, state = plant

    class Events:
        received = []

        def event_notification(self, event):
            Events.received.append(int(event.Sequence))

    async def body():
        viewer = await connect(server.url, state, "viewer")
        surrogate = await connect(server.url, state, "surrogate")
        try:
            idx = await viewer.get_namespace_index(NS)
            chain = await viewer.nodes.server.get_referenced_nodes(
                ua.ObjectIds.HasNotifier, ua.BrowseDirection.Forward)
            subscription = await viewer.create_subscription(50, Events())
            event_type = viewer.get_node(ua.NodeId("BinDischargedEventType", idx))
            await subscription.subscribe_events(viewer.nodes.server, event_type, queuesize=1000)
            refresh = await viewer.get_node(ua.ObjectIds.ConditionType).call_method(
                ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh),
                ua.Variant(subscription.subscription_id, ua.VariantType.UInt32))
            await surrogate.get_node(ua.NodeId("Plant", idx)).call_method(
                ua.NodeId("Plant.AdvanceTime", idx), ua.Variant(40.0, ua.VariantType.Double))
            await asyncio.sleep(1.0)
            return [n.nodeid.Identifier for n in chain], refresh
        finally:
            await surrogate.disconnect()
            await viewer.disconnect()

    chain, refresh = asyncio.run(body())
    assert "Plant" in chain  # Server -HasNotifier-> Plant -HasNotifier-> SP201
    assert refresh is None or refresh == []  # ConditionRefresh is Good for a viewer
    received = Events.received
    assert len(received) >= 15  # CV101's first bin arrives after 20 s: ~1 bin per s
    assert received == list(range(received[0], received[0] + len(received)))


def test_history_read_of_the_setpoint_and_the_belt_scales(plant):
    async def body(client, node):
        for value in (310.0, 320.0):
            await node("Plant.SP201.DischargeRateSetpoint").write_value(
                ua.DataValue(ua.Variant(value, ua.VariantType.Double)))
            await asyncio.sleep(0.2)
        start, end = datetime.now(timezone.utc) - timedelta(hours=1), \
            datetime.now(timezone.utc) + timedelta(minutes=1)
        setpoints = await node("Plant.SP201.DischargeRateSetpoint").read_raw_history(start, end)
        flows = await node("Plant.CV101.Totalizer").read_raw_history(start, end)
        return [v.Value.Value for v in setpoints], [v.Value.Value for v in flows]

    setpoints, totals = _run(plant, "operator", body)
    assert setpoints[-2:] == [310.0, 320.0]
    assert totals and totals == sorted(totals) and totals[-1] > 0  # the earlier tests' bins


def test_history_read_events_gives_back_the_bins_filtered_by_time(plant):
    """HistoryReadEvents on SP201 and on the Server object (UaExpert's event history
    view asks the Server): every bin discharged in a time window, with its fields,
    nothing from outside the window."""
    server, state = plant

    async def body():
        surrogate = await connect(server.url, state, "surrogate")
        viewer = await connect(server.url, state, "viewer")
        try:
            idx = await viewer.get_namespace_index(NS)
            plant_node = surrogate.get_node(ua.NodeId("Plant", idx))
            advance = ua.NodeId("Plant.AdvanceTime", idx)
            await plant_node.call_method(advance, ua.Variant(30.0, ua.VariantType.Double))
            await asyncio.sleep(0.3)
            middle = datetime.now(timezone.utc)
            await asyncio.sleep(0.3)
            await plant_node.call_method(advance, ua.Variant(10.0, ua.VariantType.Double))
            end = datetime.now(timezone.utc) + timedelta(seconds=1)
            event_type = viewer.get_node(ua.NodeId("BinDischargedEventType", idx))
            sp201 = viewer.get_node(ua.NodeId("Plant.SP201", idx))
            notifier = await sp201.read_attribute(ua.AttributeIds.EventNotifier)
            early = await sp201.read_event_history(middle - timedelta(hours=1), middle,
                                                   evtypes=event_type)
            late = await sp201.read_event_history(middle, end, evtypes=event_type)
            via_server = await viewer.nodes.server.read_event_history(
                middle - timedelta(hours=1), end, evtypes=event_type)
            pending = await viewer.get_node(
                ua.NodeId("Plant.SP201.Inbound.PendingTrackingIds", idx)).read_value()
            return notifier.Value.Value, early, late, via_server, pending
        finally:
            await viewer.disconnect()
            await surrogate.disconnect()

    notifier, early, late, via_server, pending = asyncio.run(body())
    assert notifier & ua.EventNotifierType.HistoryRead
    assert early and late  # bins before and after the middle of the run
    assert all(e.Time <= datetime.now(timezone.utc) for e in early + late)
    early_seq, late_seq = [e.Sequence for e in early], [e.Sequence for e in late]
    assert max(early_seq) < min(late_seq)  # the time filter splits the run
    everything = early_seq + late_seq
    assert everything == list(range(everything[0], everything[0] + len(everything)))
    assert [e.Sequence for e in via_server] == everything
    # the fields are the bins': the same tracking ids as the (unacknowledged) pending list
    assert [e.TrackingId for e in early + late] == list(pending)[-len(everything):]
    assert all(e.Mass > 0 and 0 <= e.Grade <= 1 and e.DischargeTime > 0 for e in early + late)


def test_index_range_reads_part_of_an_array(plant):
    """Part 4, 7.22 NumericRange on a Read (the stockpile client reads only the
    pending records it has not seen): a range gives that part, an end past the
    array is cut, a start past it is BadIndexRangeNoData, a reversed range is
    BadIndexRangeInvalid."""
    server, state = plant

    async def body():
        surrogate = await connect(server.url, state, "surrogate")
        try:
            idx = await surrogate.get_namespace_index(NS)
            await surrogate.get_node(ua.NodeId("Plant", idx)).call_method(
                ua.NodeId("Plant.AdvanceTime", idx), ua.Variant(30.0, ua.VariantType.Double))
            node = ua.NodeId("Plant.SP201.Inbound.PendingSequence", idx)
            whole = await surrogate.get_node(node).read_value()
            params = ua.ReadParameters()
            for text in ("2:4", f"3:{len(whole) + 100}", f"{len(whole)}:{len(whole) + 5}", "4:2"):
                item = ua.ReadValueId()
                item.NodeId, item.AttributeId, item.IndexRange = node, ua.AttributeIds.Value, text
                params.NodesToRead.append(item)
            return whole, await surrogate.uaclient.read(params)
        finally:
            await surrogate.disconnect()

    whole, (part, tail, past, reversed_) = asyncio.run(body())
    assert len(whole) >= 5
    assert part.Value.Value == whole[2:5] and tail.Value.Value == whole[3:]
    assert past.StatusCode.value == ua.StatusCodes.BadIndexRangeNoData
    assert reversed_.StatusCode.value == ua.StatusCodes.BadIndexRangeInvalid
