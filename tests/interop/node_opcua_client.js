// Interoperability check: node-opcua (a client no one here wrote) against the
// mock 800xA server over Basic256Sha256 SignAndEncrypt.
// Usage: node node_opcua_client.js CONFIG.json   -> prints one JSON result line.
const fs = require("fs");
const { secureClient } = require("./secure_client");
const {
  AttributeIds, DataType, UserTokenType, TimestampsToReturn, ClientSubscription,
  ClientMonitoredItem, constructEventFilter,
} = require("node-opcua");

async function main() {
  const cfg = JSON.parse(fs.readFileSync(process.argv[2], "utf8"));
  const client = await secureClient(cfg, "node-opcua interop");
  const result = {};
  await client.connect(cfg.url);
  const ns = cfg.namespace_index;
  const id = (name) => `ns=${ns};s=${name}`;

  const operator = await client.createSession({
    type: UserTokenType.UserName, userName: "operator", password: cfg.operator_password });
  const browsed = await operator.browse(id("Plant"));
  result.browse = browsed.references.map((r) => r.browseName.name).sort();
  const bins = await operator.read([
    { nodeId: id("Plant.CV101.BinTrackingIds"), attributeId: AttributeIds.Value },
    { nodeId: id("Plant.CV101.BinMasses"), attributeId: AttributeIds.Value },
  ]);
  result.bin_tracking_ids = Array.from(bins[0].value.value, (v) => Number(v[1] !== undefined ? v[1] : v));
  result.bin_masses = Array.from(bins[1].value.value);

  const subscription = ClientSubscription.create(operator, {
    requestedPublishingInterval: 100, requestedLifetimeCount: 600, requestedMaxKeepAliveCount: 20,
    maxNotificationsPerPublish: 1000, publishingEnabled: true, priority: 10 });
  const filter = constructEventFilter([`${ns}:Sequence`, `${ns}:TrackingId`, `${ns}:Mass`]);
  const item = ClientMonitoredItem.create(subscription,
    { nodeId: id("Plant.SP201"), attributeId: AttributeIds.EventNotifier },
    { queueSize: 1000, filter, discardOldest: false, samplingInterval: 0 },
    TimestampsToReturn.Neither);
  const events = [];
  item.on("changed", (fields) => {
    const seq = fields[0].value;
    events.push({ sequence: Number(Array.isArray(seq) ? seq[1] : seq), mass: fields[2].value });
  });
  await new Promise((resolve) => setTimeout(resolve, cfg.listen_ms));
  result.events = events;
  await subscription.terminate();

  // A refused request comes back as a per-node status or, for a whole request
  // the role may not make, as a service fault: report the status name either way.
  const write = async (session, value) => {
    try {
      return (await session.write({
        nodeId: id("Plant.SP201.DischargeRateSetpoint"), attributeId: AttributeIds.Value,
        value: { value: { dataType: DataType.Double, value } } })).name;
    } catch (err) {
      const header = err.response && err.response.responseHeader;
      if (header && header.serviceResult) return header.serviceResult.name;
      const match = /Bad\w+/.exec(String(err.message));
      return match ? match[0] : `error: ${err.message}`;
    }
  };
  result.operator_write = await write(operator, 321.0);
  result.operator_write_out_of_range = await write(operator, 5000.0);
  // one session per secure channel (the server refuses a second one): the viewer
  // connects with its own client
  const viewerClient = await secureClient(cfg, "node-opcua interop viewer");
  await viewerClient.connect(cfg.url);
  const viewer = await viewerClient.createSession({
    type: UserTokenType.UserName, userName: "viewer", password: cfg.viewer_password });
  result.viewer_write = await write(viewer, 111.0);
  result.setpoint_after = (await viewer.read({
    nodeId: id("Plant.SP201.DischargeRateSetpoint"), attributeId: AttributeIds.Value })).value.value;
  await viewer.close();
  await viewerClient.disconnect();
  await operator.close();
  await client.disconnect();
  console.log("RESULT " + JSON.stringify(result));
}

main().catch((err) => { console.error(err); process.exit(1); });
