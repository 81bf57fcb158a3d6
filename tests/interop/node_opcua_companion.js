// Companion-specification names as node-opcua browses them: the type definition
// of CV101 and CV301, its supertype chain, a belt scale's MassFlowRate by browse
// path and the type of a feed lot.
// Usage: node node_opcua_companion.js CONFIG.json   -> prints one JSON result line.
const fs = require("fs");
const { secureClient } = require("./secure_client");
const { AttributeIds, UserTokenType, BrowseDirection, makeBrowsePath } = require("node-opcua");

async function main() {
  const cfg = JSON.parse(fs.readFileSync(process.argv[2], "utf8"));
  const client = await secureClient(cfg, "node-opcua companion check");
  await client.connect(cfg.url);
  const ns = cfg.namespace_index;
  const id = (name) => `ns=${ns};s=${name}`;
  const session = await client.createSession({
    type: UserTokenType.UserName, userName: "viewer", password: cfg.viewer_password });
  const name = async (nodeId) =>
    (await session.read({ nodeId, attributeId: AttributeIds.BrowseName })).value.value.name;
  const typeDefinition = async (nodeId) => {
    const r = await session.browse({ nodeId, referenceTypeId: "HasTypeDefinition",
      browseDirection: BrowseDirection.Forward, includeSubtypes: false, resultMask: 63 });
    return r.references[0].nodeId;
  };
  const result = { type_definitions: {}, supertypes: [] };
  for (const belt of ["CV101", "CV301"]) {
    result.type_definitions[belt] = await name(await typeDefinition(id(`Plant.${belt}`)));
  }
  let type = await typeDefinition(id("Plant.CV101"));
  for (;;) {
    result.supertypes.push(await name(type));
    const up = await session.browse({ nodeId: type, referenceTypeId: "HasSubtype",
      browseDirection: BrowseDirection.Inverse, includeSubtypes: false, resultMask: 63 });
    if (up.references.length === 0) break;
    type = up.references[0].nodeId;
    if (result.supertypes.length > 10) break;
  }
  result.supertypes = result.supertypes.slice(0, result.supertypes.indexOf("BaseObjectType") + 1);
  const found = await session.translateBrowsePath(makeBrowsePath(id("Plant.CV101"),
    `/${ns}:Components/${ns}:BeltScale/${ns}:Monitoring/${ns}:Process/${ns}:MassFlowRate.EngineeringUnits`));
  const units = await session.read({ nodeId: found.targets[0].targetId, attributeId: AttributeIds.Value });
  result.mass_flow_rate_units = units.value.value.displayName.text;
  result.feed_lot_type = await name(await typeDefinition(id("Plant.MaterialLots.FeedLot1")));
  await session.close();
  await client.disconnect();
  console.log("RESULT " + JSON.stringify(result));
}

main().catch((err) => { console.error(err); process.exit(1); });
