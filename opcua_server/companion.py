"""Names and structure of the published companion specifications, in our namespace.

An integrator who knows the OPC UA companion specifications finds their type
names and browse paths here; the types are our own definitions in
``urn:minetwin:mock800xa``, not the specifications' nodesets (no DI,
Machinery or Mining General namespace is loaded, and nothing is claimed to
be conformant):

* **OPC 40563-4** (Mining - Transport Dumping - Part 4: Conveying, 1.0.0):
  ``BeltConveyorType`` and ``BeltScaleType``, both subtypes of
  ``MiningEquipmentType`` (OPC 40560, abstract), each with a
  ``MiningEquipmentIdentification`` add-in (``AssetId``, ``DeviceClass``);
  a belt conveyor's ``Components`` add-in holds its ``BeltScale``, whose
  ``Monitoring/Process`` holds ``MassFlowRate`` and ``BeltSpeedScale``
  (AnalogUnitType, Double), as in the specification. ``Totalizer`` is ours:
  OPC 40563-4's BeltScaleType has none (a totalizer is in OPC 40200 Weighing
  Technology's ContinuousScaleType, as a TotalizerType object).
* **OPC 10030** (ISA-95 Common Object Model, 1.00): ``MaterialLotType`` and
  ``MaterialSublotType`` under the abstract ``ISA95ObjectType``, their
  attributes linked by ``HasISA95Attribute`` (a subtype of HasComponent):
  ``Quantity``, ``Status``, ``StorageLocation`` from OPC 10030; ``ID``,
  ``Description`` and ``UnitOfMeasure`` from the ISA-95 material lot object
  (OPC 10030 names a lot by its Object; ISA95-JOBCONTROL's
  ISA95MaterialDataType carries MaterialLotID, Description, Quantity, UoM).
  ``MaterialSublotListType`` is ours: the bins on a belt as sublots, one
  array element per bin, because one Object per bin would cost an AddNodes
  and a DeleteNodes per bin (1,000 bins/s at the highest benchmark rate).

The values are copies of the plant's own nodes (``Plant.CV101.MassFlow`` ->
``...BeltScale.Monitoring.Process.MassFlowRate``), written with the belt
scales once per wall second (every tick in lockstep); every existing node id
is unchanged.
"""

from __future__ import annotations

from typing import Awaitable, Callable

from asyncua import ua

from opcua_server.node_attributes import read_only_variable

D, U, S = ua.VariantType.Double, ua.VariantType.UInt64, ua.VariantType.String
_MANDATORY, _OPTIONAL = True, False

LOT_ATTRIBUTES = (
    # name, variant, unit, description
    ("ID", S, None, "identification of the material (ISA-95 material lot/sublot ID)"),
    ("Description", S, None, "what the material is"),
    ("Quantity", D, "kg", "quantity of the material"),
    ("UnitOfMeasure", S, None, "unit of measure of Quantity (UNECE symbol)"),
    ("Status", S, None, "status of the material"),
    ("StorageLocation", S, None, "where the material is"),
)
"""The attributes of MaterialLotType and MaterialSublotType (all optional)."""


class CompanionModel:
    """The companion-specification types and their instances in the plant.

    Parameters
    ----------
    server : asyncua.Server
        The plant's server (types and instances are added through its
        internal session).
    idx : int
        Our namespace index.
    eu : callable
        ``eu(unit) -> ua.EUInformation`` for a unit key (``"kg"``, ``"kg/s"``, ``"m/s"``).
    write : callable
        ``await write(node_id_string, value, variant)``: a value with timestamps.
    """

    def __init__(self, server, idx: int, eu: Callable[[str], ua.EUInformation],
                 write: Callable[[str, object, ua.VariantType], Awaitable[None]]):
        self.server, self.idx, self.eu, self.write = server, idx, eu, write
        self.types: dict[str, ua.NodeId] = {}

    def nid(self, name: str) -> ua.NodeId:
        return ua.NodeId(name, self.idx)

    def qn(self, name: str) -> ua.QualifiedName:
        return ua.QualifiedName(name, self.idx)

    # ----------------------------------------------------------------- types
    async def add_types(self) -> None:
        """The ObjectTypes and the HasISA95Attribute ReferenceType."""
        s = self.server
        base = s.nodes.base_object_type
        has_attribute = await s.get_node(ua.ObjectIds.HasComponent).add_reference_type(
            self.nid("HasISA95Attribute"), self.qn("HasISA95Attribute"), symmetric=False,
            inversename="ISA95AttributeOf")
        self.types["HasISA95Attribute"] = has_attribute.nodeid

        mining = await self._object_type(
            base, "MiningEquipmentType", abstract=True,
            text="any mining equipment (name and add-in after OPC 40560 MiningEquipmentType)")
        ident = await self._child_object(
            mining, "MiningEquipmentIdentification", ua.ObjectIds.BaseObjectType,
            ua.ObjectIds.HasAddIn, _MANDATORY, "identification of the equipment")
        for name, text in (("AssetId", "the plant's tag of the equipment"),
                           ("DeviceClass", "what kind of equipment it is")):
            await self._variable(ident, name, "", S, text, _MANDATORY, prop=True)

        scale = await self._object_type(
            mining, "BeltScaleType",
            text="belt scale of a conveyor (OPC 40563-4 BeltScaleType: Monitoring/Process)")
        monitoring = await self._child_object(scale, "Monitoring", ua.ObjectIds.BaseObjectType,
                                              ua.ObjectIds.HasComponent, _OPTIONAL,
                                              "current state of the process")
        process = await self._child_object(monitoring, "Process", ua.ObjectIds.FolderType,
                                           ua.ObjectIds.HasComponent, _OPTIONAL,
                                           "process values of the belt scale")
        for name, unit, text in (
                ("MassFlowRate", "kg/s", "mass flow over the scale, averaged over the last 10 s"),
                ("BeltSpeedScale", "m/s", "belt speed at the scale"),
                ("Totalizer", "kg", "total mass over the scale (not in OPC 40563-4)")):
            await self._variable(process, name, 0.0, D, text, _OPTIONAL, unit=unit)

        conveyor = await self._object_type(
            mining, "BeltConveyorType",
            text="belt conveyor (OPC 40563-4 BeltConveyorType: Components add-in with the "
                 "BeltScale)")
        await self._child_object(conveyor, "Components", ua.ObjectIds.FolderType,
                                 ua.ObjectIds.HasAddIn, _OPTIONAL,
                                 "the identifiable components of the equipment")

        isa95 = await self._object_type(
            base, "ISA95ObjectType", abstract=True,
            text="ISA-95 object (name after OPC 10030 ISA95ObjectType)")
        for name, text in (("MaterialLotType", "a uniquely identified amount of material "
                                               "(name after OPC 10030 MaterialLotType)"),
                           ("MaterialSublotType", "a uniquely identified part of a material "
                                                  "lot (name after OPC 10030 "
                                                  "MaterialSublotType)")):
            lot_type = await self._object_type(isa95, name, text=text)
            for attr, vtype, unit, attr_text in LOT_ATTRIBUTES:
                await self._variable(lot_type, attr, ua.get_default_value(vtype), vtype,
                                     attr_text, _OPTIONAL, unit=unit,
                                     reference=has_attribute.nodeid)

        sublots = await self._object_type(
            base, "MaterialSublotListType",
            text="material sublots as arrays, one element per sublot (ours: one Object per "
                 "bin would be an AddNodes and a DeleteNodes per bin)")
        for name, vtype, unit, text in (
                ("ID", U, None, "tracking id of each sublot"),
                ("Quantity", D, "kg", "mass of each sublot, one per ID")):
            await self._variable(sublots, name, [], vtype, text, _MANDATORY, unit=unit, dims=0)
        for name, text in (("UnitOfMeasure", "unit of measure of Quantity"),
                           ("StorageLocation", "where the sublots are")):
            await self._variable(sublots, name, "", S, text, _MANDATORY, prop=True)

    async def _object_type(self, parent, name: str, *, text: str, abstract: bool = False):
        node = await parent.add_object_type(self.nid(name), self.qn(name))
        await node.write_attribute(ua.AttributeIds.Description,
                                   ua.DataValue(ua.LocalizedText(text)))
        if abstract:
            await node.write_attribute(ua.AttributeIds.IsAbstract,
                                       ua.DataValue(ua.Variant(True, ua.VariantType.Boolean)))
        self.types[name] = node.nodeid
        return node

    async def _child_object(self, parent, name: str, type_id: int, reference: int,
                            mandatory: bool, text: str):
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = self.nid(f"{parent.nodeid.Identifier}.{name}")
        item.BrowseName = self.qn(name)
        item.NodeClass = ua.NodeClass.Object
        item.ParentNodeId = parent.nodeid
        item.ReferenceTypeId = ua.NodeId(reference)
        item.TypeDefinition = ua.NodeId(type_id)
        attrs = ua.ObjectAttributes()
        attrs.DisplayName = ua.LocalizedText(name)
        attrs.Description = ua.LocalizedText(text)
        item.NodeAttributes = attrs
        return await self._add(item, mandatory)

    async def _variable(self, parent, name: str, value, vtype, text: str, mandatory: bool, *,
                        unit=None, dims=None, prop=False, reference=None):
        """An instance declaration: a property, or a data variable (AnalogUnitType
        with an EngineeringUnits property if ``unit``)."""
        nodeid = self.nid(f"{parent.nodeid.Identifier}.{name}")
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = nodeid
        item.BrowseName = self.qn(name)
        item.NodeClass = ua.NodeClass.Variable
        item.ParentNodeId = parent.nodeid
        item.ReferenceTypeId = reference or ua.NodeId(
            ua.ObjectIds.HasProperty if prop else ua.ObjectIds.HasComponent)
        item.TypeDefinition = ua.NodeId(
            ua.ObjectIds.PropertyType if prop else
            ua.ObjectIds.AnalogUnitType if unit else ua.ObjectIds.BaseDataVariableType)
        attrs = read_only_variable(name, text, value, vtype, dims)
        item.NodeAttributes = attrs
        node = await self._add(item, mandatory)
        if unit is not None:
            eu = await node.add_property(self.nid(f"{nodeid.Identifier}.EngineeringUnits"),
                                         ua.QualifiedName("EngineeringUnits", 0),
                                         ua.Variant(self.eu(unit)),
                                         datatype=ua.NodeId(ua.ObjectIds.EUInformation))
            await eu.set_modelling_rule(_MANDATORY)
        return node

    async def _add(self, item: ua.AddNodesItem, mandatory: bool):
        result = (await self.server.iserver.isession.add_nodes([item]))[0]
        result.StatusCode.check()
        node = self.server.get_node(item.RequestedNewNodeId)
        await node.set_modelling_rule(mandatory)
        return node

    # ------------------------------------------------------------- instances
    def belt_type(self) -> ua.NodeId:
        """Type definition of CV101 and CV301 (``add_object(..., objecttype=)``)."""
        return self.types["BeltConveyorType"]

    async def add_belt_scale(self, belt: str, where: str) -> None:
        """The belt scale of an instantiated belt conveyor (``Plant.<belt>``) and
        the belt's sublot list."""
        s, base = self.server, f"Plant.{belt}"
        await self._identify(base, belt, "belt conveyor")
        components = s.get_node(self.nid(f"{base}.Components"))
        scale = await components.add_object(self.nid(f"{base}.Components.BeltScale"),
                                            self.qn("BeltScale"),
                                            objecttype=self.types["BeltScaleType"])
        await scale.write_attribute(ua.AttributeIds.Description, ua.DataValue(
            ua.LocalizedText(f"belt scale of {belt} {where}")))
        await self._identify(f"{base}.Components.BeltScale", f"{belt}-WI", "belt scale")
        sublots = await s.get_node(self.nid(base)).add_object(
            self.nid(f"{base}.MaterialSublots"), self.qn("MaterialSublots"),
            objecttype=self.types["MaterialSublotListType"])
        await sublots.write_attribute(ua.AttributeIds.Description, ua.DataValue(
            ua.LocalizedText(f"the tracked material on {belt} as ISA-95 sublots (same "
                             f"tracking ids and masses as the bin arrays)")))
        await self.write(f"{base}.MaterialSublots.UnitOfMeasure", "kg", S)
        await self.write(f"{base}.MaterialSublots.StorageLocation", belt, S)

    async def _identify(self, base: str, asset_id: str, device_class: str) -> None:
        await self.write(f"{base}.MiningEquipmentIdentification.AssetId", asset_id, S)
        await self.write(f"{base}.MiningEquipmentIdentification.DeviceClass", device_class, S)

    async def add_feed_lots(self, plant, lots: list[dict]) -> None:
        """``Plant.MaterialLots``: one MaterialLotType Object per lot of the feed
        schedule (a bounded number, from the configuration)."""
        folder = await plant.add_folder(self.nid("Plant.MaterialLots"), self.qn("MaterialLots"))
        await folder.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.LocalizedText(
            "the lots of the feed schedule (config [[feed.lots]]), filling CV101's bins in turn")))
        self._lot_ends, self._lot_status = [], []
        end = 0.0
        for k, lot in enumerate(lots, start=1):
            base = f"Plant.MaterialLots.FeedLot{k}"
            node = await folder.add_object(self.nid(base), self.qn(f"FeedLot{k}"),
                                           objecttype=self.types["MaterialLotType"])
            await node.write_attribute(ua.AttributeIds.Description, ua.DataValue(
                ua.LocalizedText(f"lot {k} of the feed schedule (source {lot['source']})")))
            planned = float(lot["feed_rate_kg_s"]) * float(lot["duration_s"])
            for name, value, vtype in (
                    ("ID", f"FEED-{k}", S),
                    ("Description", f"source {lot['source']}: {lot['feed_rate_kg_s']} kg/s for "
                                    f"{lot['duration_s']} s of each pass of the schedule, grade "
                                    f"{lot['grade']}, hardness {lot['hardness']}", S),
                    ("Quantity", planned, D), ("UnitOfMeasure", "kg", S),
                    ("StorageLocation", "CV101 loading point", S), ("Status", "waiting", S)):
                await self.write(f"{base}.{name}", value, vtype)
            end += float(lot["duration_s"])
            self._lot_ends.append(end)
            self._lot_status.append("waiting")

    # ---------------------------------------------------------------- values
    async def publish(self, process) -> None:
        """Copy the belt scales, the feed lot being fed and the belts' sublots
        (called with the belt scales: once per wall second, every tick in lockstep)."""
        w = self.write
        for belt, totalizer, b in (("CV101", process.mass_in_kg, process.cv101),
                                   ("CV301", process.mass_out_kg, process.cv301)):
            base = f"Plant.{belt}.Components.BeltScale.Monitoring.Process"
            await w(f"{base}.MassFlowRate", process.mass_flow(belt.lower()), D)
            await w(f"{base}.BeltSpeedScale", float(b.speed_m_s), D)
            await w(f"{base}.Totalizer", float(totalizer), D)
        b = process.cv101
        full = b.tracking_id != 0
        await w("Plant.CV101.MaterialSublots.ID", b.tracking_id[full].tolist(), U)
        await w("Plant.CV101.MaterialSublots.Quantity", b.mass[full].tolist(), D)
        tids, masses = [], []
        for contents in process.cv301_contents:
            tids.extend(contents), masses.extend(contents.values())
        await w("Plant.CV301.MaterialSublots.ID", [int(t) for t in tids], U)
        await w("Plant.CV301.MaterialSublots.Quantity", [float(m) for m in masses], D)
        await self._publish_lot_status(process.time)

    async def _publish_lot_status(self, t: float) -> None:
        period = self._lot_ends[-1]
        current = next(k for k, end in enumerate(self._lot_ends) if t % period < end or
                       k == len(self._lot_ends) - 1)
        for k, old in enumerate(self._lot_status):
            new = "feeding" if k == current else "waiting"
            if new != old:
                await self.write(f"Plant.MaterialLots.FeedLot{k + 1}.Status", new, S)
                self._lot_status[k] = new
