"""Companion-specification names, as an integrator's client browses them.

A real server (lockstep, 127.0.0.1, free port); an asyncua client browses the
type hierarchy (CV101 and CV301 are ``BeltConveyorType``, OPC 40563-4 names;
the feed lots are ``MaterialLotType``, OPC 10030 names) and reads that the
spec-named nodes carry the same values as the plant's own nodes. node-opcua
browses the same hierarchy (``tests/interop/node_opcua_companion.js``).
"""

import asyncio

import pytest
from asyncua import ua

from minetwin.harness import ServerProcess, connect, prepare_state
from tests.test_opcua_interop import SCRIPT, _pem_certificate, _run_node, node_opcua  # noqa: F401

NS = "urn:minetwin:mock800xa"
LOT_ATTRIBUTES = {"ID", "Description", "Quantity", "UnitOfMeasure", "Status", "StorageLocation"}
ADVANCED_S = 70.0  # into the second feed lot (60 s each)


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    root = tmp_path_factory.mktemp("companion")
    state = prepare_state(root / "state")
    server = ServerProcess(root, state, lockstep=True)
    try:
        async def advance():
            client = await connect(server.url, state, "surrogate")
            try:
                idx = await client.get_namespace_index(NS)
                await client.get_node(ua.NodeId("Plant", idx)).call_method(
                    ua.NodeId("Plant.AdvanceTime", idx), ADVANCED_S)
            finally:
                await client.disconnect()
        asyncio.run(advance())
        yield server, state
    finally:
        server.stop()


def _run(plant, body):
    server, state = plant

    async def go():
        client = await connect(server.url, state, "viewer")
        try:
            idx = await client.get_namespace_index(NS)
            return await body(client, idx)
        finally:
            await client.disconnect()
    return asyncio.run(go())


async def _name(client, nodeid) -> str:
    return (await client.get_node(nodeid).read_browse_name()).Name


async def _supertype(client, type_id) -> ua.NodeId:
    refs = await client.get_node(type_id).get_references(
        ua.ObjectIds.HasSubtype, ua.BrowseDirection.Inverse)
    assert len(refs) == 1
    return refs[0].NodeId


async def _children(client, nodeid, reference=ua.ObjectIds.HierarchicalReferences) -> dict:
    """``{browse name: reference description}`` of a node's forward references."""
    refs = await client.get_node(nodeid).get_references(reference, ua.BrowseDirection.Forward,
                                                        includesubtypes=True)
    return {r.BrowseName.Name: r for r in refs}


async def _modelling_rule(client, nodeid) -> str:
    refs = await client.get_node(nodeid).get_references(ua.ObjectIds.HasModellingRule)
    return await _name(client, refs[0].NodeId)


def test_belts_are_belt_conveyors_with_a_belt_scale(plant):
    async def body(client, idx):
        conveyor, scale = ua.NodeId("BeltConveyorType", idx), ua.NodeId("BeltScaleType", idx)
        mining = ua.NodeId("MiningEquipmentType", idx)
        for belt in ("CV101", "CV301"):
            node = client.get_node(ua.NodeId(f"Plant.{belt}", idx))
            assert await node.read_type_definition() == conveyor
            ident = await node.get_child([f"{idx}:MiningEquipmentIdentification", f"{idx}:AssetId"])
            assert await ident.read_value() == belt
            instance = await node.get_child([f"{idx}:Components", f"{idx}:BeltScale"])
            assert await instance.read_type_definition() == scale
        # the hierarchy: BeltConveyorType, BeltScaleType -> MiningEquipmentType (abstract)
        # -> BaseObjectType
        assert await _supertype(client, conveyor) == mining
        assert await _supertype(client, scale) == mining
        assert await _supertype(client, mining) == ua.NodeId(ua.ObjectIds.BaseObjectType)
        abstract = (await client.get_node(mining).read_attribute(
            ua.AttributeIds.IsAbstract)).Value.Value
        assert abstract is True
        # declared components, with the specification's reference types and rules
        declared = await _children(client, conveyor)
        assert declared["Components"].ReferenceTypeId == ua.NodeId(ua.ObjectIds.HasAddIn)
        assert await _modelling_rule(client, declared["Components"].NodeId) == "Optional"
        inherited = await _children(client, mining)
        ident = inherited["MiningEquipmentIdentification"]
        assert ident.ReferenceTypeId == ua.NodeId(ua.ObjectIds.HasAddIn)
        assert await _modelling_rule(client, ident.NodeId) == "Mandatory"
        assert {"AssetId", "DeviceClass"} <= set(await _children(client, ident.NodeId))
        process = await client.get_node(scale).get_child([f"{idx}:Monitoring", f"{idx}:Process"])
        assert set(await _children(client, process.nodeid)) == {
            "MassFlowRate", "BeltSpeedScale", "Totalizer"}
        return True
    assert _run(plant, body)


def test_the_belt_scale_shows_the_plants_own_values(plant):
    async def body(client, idx):
        out = {}
        for belt in ("CV101", "CV301"):
            base = client.get_node(ua.NodeId(f"Plant.{belt}", idx))
            process = await base.get_child([f"{idx}:Components", f"{idx}:BeltScale",
                                            f"{idx}:Monitoring", f"{idx}:Process"])
            names = ("MassFlowRate", "Totalizer", "BeltSpeedScale")
            spec = [await process.get_child(f"{idx}:{n}") for n in names]
            own = [client.get_node(ua.NodeId(f"Plant.{belt}.{n}", idx))
                   for n in ("MassFlow", "Totalizer", "BeltSpeed")]
            values = await client.read_values(spec + own)  # one Read: one snapshot
            units = (await (await spec[0].get_child("0:EngineeringUnits")).read_value()).DisplayName.Text
            out[belt] = (values[:3], values[3:], units)
        return out
    out = _run(plant, body)
    for belt, (spec, own, units) in out.items():
        assert spec == own, belt
        assert units == "kg/s"
    assert out["CV101"][0][1] > 0.0  # bins have reached the head in 70 s


def test_feed_lots_and_bins_in_isa95_lot_structure(plant):
    async def body(client, idx):
        isa95 = ua.NodeId("ISA95ObjectType", idx)
        has_attribute = ua.NodeId("HasISA95Attribute", idx)
        out = {"attributes": {}, "lots": {}}
        assert await _supertype(client, isa95) == ua.NodeId(ua.ObjectIds.BaseObjectType)
        assert (await client.get_node(isa95).read_attribute(
            ua.AttributeIds.IsAbstract)).Value.Value is True
        assert await _supertype(client, has_attribute) == ua.NodeId(ua.ObjectIds.HasComponent)
        for name in ("MaterialLotType", "MaterialSublotType"):
            type_id = ua.NodeId(name, idx)
            assert await _supertype(client, type_id) == isa95
            out["attributes"][name] = set(await _children(client, type_id, has_attribute))
        lots = await _children(client, ua.NodeId("Plant.MaterialLots", idx))
        for name, ref in sorted(lots.items()):
            assert ref.TypeDefinition == ua.NodeId("MaterialLotType", idx)
            attrs = await _children(client, ref.NodeId, has_attribute)
            out["lots"][name] = dict(zip(attrs, await client.read_values(
                [client.get_node(r.NodeId) for r in attrs.values()])))
        read = lambda *names: client.read_values(  # noqa: E731
            [client.get_node(ua.NodeId(n, idx)) for n in names])
        out["cv101"] = await read("Plant.CV101.MaterialSublots.ID",
                                  "Plant.CV101.MaterialSublots.Quantity",
                                  "Plant.CV101.BinTrackingIds", "Plant.CV101.BinMasses",
                                  "Plant.CV101.MaterialSublots.StorageLocation")
        out["cv301"] = await read("Plant.CV301.MaterialSublots.ID",
                                  "Plant.CV301.MaterialSublots.Quantity",
                                  "Plant.CV301.ContentsTrackingIds", "Plant.CV301.ContentsMasses")
        return out
    out = _run(plant, body)
    assert out["attributes"] == {"MaterialLotType": LOT_ATTRIBUTES,
                                 "MaterialSublotType": LOT_ATTRIBUTES}
    lots = out["lots"]
    assert sorted(lots) == ["FeedLot1", "FeedLot2", "FeedLot3"]  # the default schedule
    assert [lots[k]["ID"] for k in sorted(lots)] == ["FEED-1", "FEED-2", "FEED-3"]
    assert lots["FeedLot1"]["Quantity"] == pytest.approx(250.0 * 60.0)
    assert lots["FeedLot1"]["UnitOfMeasure"] == "kg"
    assert {k: v["Status"] for k, v in lots.items()} == {
        "FeedLot1": "waiting", "FeedLot2": "feeding", "FeedLot3": "waiting"}  # at 70 s
    ids, quantities, bin_ids, bin_masses, location = out["cv101"]
    full = [i for i, t in enumerate(bin_ids) if t != 0]
    assert ids == [bin_ids[i] for i in full] and len(ids) == 20  # the belt is full at 70 s
    assert quantities == [bin_masses[i] for i in full]
    assert location == "CV101"
    ids3, quantities3, contents_ids, contents_masses = out["cv301"]
    assert ids3 == contents_ids and quantities3 == contents_masses


def test_node_opcua_sees_the_same_type_hierarchy(node_opcua, plant, tmp_path):  # noqa: F811
    server, state = plant

    async def index():
        client = await connect(server.url, state, "viewer")
        try:
            return await client.get_namespace_index(NS)
        finally:
            await client.disconnect()
    from opcua_protocol import APPLICATION_URI_CLIENT
    result = _run_node(node_opcua, SCRIPT.with_name("node_opcua_companion.js"), {
        "url": server.url, "workdir": str(tmp_path), "application_uri": APPLICATION_URI_CLIENT,
        "certificate_pem": str(_pem_certificate(state, tmp_path)),
        "private_key_pem": str(state["client_key"]), "namespace_index": asyncio.run(index()),
        "viewer_password": state["passwords"]["viewer"]}, tmp_path)
    assert result["type_definitions"] == {"CV101": "BeltConveyorType",
                                          "CV301": "BeltConveyorType"}
    assert result["supertypes"] == ["BeltConveyorType", "MiningEquipmentType", "BaseObjectType"]
    assert result["mass_flow_rate_units"] == "kg/s"
    assert result["feed_lot_type"] == "MaterialLotType"
