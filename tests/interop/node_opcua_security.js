// Security checks of the mock 800xA server from node-opcua (a client no one here
// wrote): each of the defects found by an integrator, with the status it now gets.
// Usage: node node_opcua_security.js CONFIG.json   -> prints one JSON result line.
const fs = require("fs");
const path = require("path");
const {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, DataType, VariantArrayType,
  UserTokenType, ClientSubscription, ClientMonitoredItem, TimestampsToReturn,
  OPCUACertificateManager, CreateSessionRequest,
} = require("node-opcua");
const crypto = require("crypto");

// the status name of a result, a refused request (service fault) or an error message
const statusOf = (err) => {
  const header = err.response && err.response.responseHeader;
  if (header && header.serviceResult) return header.serviceResult.name;
  const match = /Bad\w+/.exec(String(err.message));
  return match ? match[0] : `error: ${err.message}`;
};
const attempt = async (action) => {
  try {
    const result = await action();
    return result && result.name ? result.name : "Good";
  } catch (err) {
    return statusOf(err);
  }
};
const u64 = (n) => [Math.floor(n / 4294967296), n % 4294967296];
const fromU64 = (v) => (Array.isArray(v) ? v[0] * 4294967296 + v[1] : Number(v));

async function main() {
  const cfg = JSON.parse(fs.readFileSync(process.argv[2], "utf8"));
  const certificateManager = new OPCUACertificateManager({
    rootFolder: path.join(cfg.workdir, "node_pki"), automaticallyAcceptUnknownCertificate: true });
  await certificateManager.initialize();
  const makeClient = (securityMode, securityPolicy) => OPCUAClient.create({
    applicationName: "node-opcua security", applicationUri: cfg.application_uri,
    securityMode, securityPolicy, certificateFile: cfg.certificate_pem,
    privateKeyFile: cfg.private_key_pem, clientCertificateManager: certificateManager,
    endpointMustExist: false, connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 200 },
  });
  const secure = () => makeClient(MessageSecurityMode.SignAndEncrypt, SecurityPolicy.Basic256Sha256);
  const login = (client, role) => client.createSession({
    type: UserTokenType.UserName, userName: role, password: cfg.passwords[role] });
  const ns = cfg.namespace_index;
  const id = (name) => `ns=${ns};s=${name}`;
  const result = {};

  // 1. identity per session: a second session on the operator's channel is refused
  const opClient = secure();
  await opClient.connect(cfg.url);
  const operator = await login(opClient, "operator");
  result.second_session = await attempt(() => login(opClient, "viewer"));
  const vClient = secure();
  await vClient.connect(cfg.url);
  const viewer = await login(vClient, "viewer");
  const sClient = secure();
  await sClient.connect(cfg.url);
  const surrogate = await login(sClient, "surrogate");

  // 2. the None channel: discovery only, no session (so no password oracle)
  const noneClient = makeClient(MessageSecurityMode.None, SecurityPolicy.None);
  // node-opcua itself will not open a session on an endpoint the server does not
  // offer, so send the CreateSessionRequest on the None channel by hand
  await noneClient.connect(cfg.url);
  result.none_discovery = (await noneClient.getEndpoints()).length;
  result.none_session = await new Promise((resolve) => noneClient.performMessageTransaction(
    new CreateSessionRequest({
      clientDescription: { applicationUri: cfg.application_uri, applicationName: { text: "x" } },
      endpointUrl: cfg.url, sessionName: "none-channel", clientNonce: crypto.randomBytes(32),
      requestedSessionTimeout: 60000, maxResponseMessageSize: 0 }),
    (err, response) => resolve(err ? statusOf(err)
      : response.responseHeader.serviceResult.name)));
  await noneClient.disconnect().catch(() => {});

  // 3. a viewer cannot delete the operator's subscription
  const subscription = ClientSubscription.create(operator, {
    requestedPublishingInterval: 50, requestedLifetimeCount: 600, requestedMaxKeepAliveCount: 20,
    maxNotificationsPerPublish: 100, publishingEnabled: true, priority: 10 });
  await new Promise((resolve) => subscription.on("started", resolve));
  let changes = 0;
  const item = ClientMonitoredItem.create(subscription,
    { nodeId: id("Plant.SP201.DischargeRateSetpoint"), attributeId: AttributeIds.Value },
    { samplingInterval: 0, queueSize: 10, discardOldest: true }, TimestampsToReturn.Both);
  item.on("changed", () => { changes += 1; });
  await new Promise((resolve) => setTimeout(resolve, 300));
  const deleted = await viewer.deleteSubscriptions({ subscriptionIds: [subscription.subscriptionId] });
  result.viewer_delete_subscription = deleted.results.map((s) => s.name);
  const before = changes;
  const write = (session, value) => attempt(async () => (await session.write({
    nodeId: id("Plant.SP201.DischargeRateSetpoint"), attributeId: AttributeIds.Value,
    value: { value } })));
  result.operator_write = await write(operator, { dataType: DataType.Double, value: 333.0 });
  await new Promise((resolve) => setTimeout(resolve, 500));
  result.operator_notified_after = changes - before;
  await subscription.terminate();

  // 4. wrongly typed writes
  result.typed_writes = [
    await write(operator, { dataType: DataType.String, value: "150" }),
    await write(operator, { dataType: DataType.Boolean, value: true }),
    await write(operator, { dataType: DataType.Int32, value: 100 }),
  ];
  result.setpoint_after = (await viewer.read({
    nodeId: id("Plant.SP201.DischargeRateSetpoint"), attributeId: AttributeIds.Value })).value.value;

  // 5, 6, 8: method arguments as the surrogate
  const pending = (await surrogate.read({
    nodeId: id("Plant.SP201.Inbound.PendingTrackingIds"), attributeId: AttributeIds.Value }))
    .value.value;
  const tid = fromU64(pending[0]);
  const nextReport = fromU64((await surrogate.read({
    nodeId: id("Plant.SP201.Outbound.LastSequence"), attributeId: AttributeIds.Value })).value.value) + 1;
  const call = async (args) => {
    const r = await surrogate.call({ objectId: id("Plant.SP201.Outbound"),
      methodId: id("Plant.SP201.Outbound.ReportOutflow"), inputArguments: args });
    return { status: r.statusCode.name, inputs: (r.inputArgumentResults || []).map((s) => s.name),
             message: r.outputArguments && r.outputArguments[0] ? r.outputArguments[0].value : null };
  };
  const arr = (dataType, value) => ({ dataType, arrayType: VariantArrayType.Array, value });
  const seq = (n) => ({ dataType: DataType.UInt64, arrayType: VariantArrayType.Scalar, value: u64(n) });
  const report = (n, mass, ids = [tid]) => [seq(n), arr(DataType.UInt64, ids.map(u64)),
    arr(DataType.Double, ids.map(() => mass)), arr(DataType.Double, ids.map(() => 0.01))];
  result.wrong_types = await call([seq(nextReport), arr(DataType.Double, [tid + 0.7]),
    arr(DataType.String, ["1.0"]), arr(DataType.Boolean, [true])]);
  result.missing = await call(report(nextReport, 1.0).slice(0, 2));
  result.too_many = await call([...report(nextReport, 1.0), seq(1)]);
  result.applied = await call(report(nextReport, 2.0));
  result.resent = await call(report(nextReport, 2.0));
  result.conflict = await call(report(nextReport, 3.0));
  const big = Array.from({ length: cfg.max_report_rows + 1 }, (_, k) => k + 1);
  result.too_long = await call(report(nextReport + 1, 1.0, big));

  // 7. access attributes as each role sees them
  const access = async (session) => ({
    // CurrentRead | CurrentWrite bits (HistoryRead is set where history is kept)
    setpoint: (await session.read({ nodeId: id("Plant.SP201.DischargeRateSetpoint"),
      attributeId: AttributeIds.UserAccessLevel })).value.value & 3,
    held_mass: (await session.read({ nodeId: id("Plant.SP201.HeldMass"),
      attributeId: AttributeIds.UserAccessLevel })).value.value & 3,
    report_executable: (await session.read({ nodeId: id("Plant.SP201.Outbound.ReportOutflow"),
      attributeId: AttributeIds.UserExecutable })).value.value,
  });
  result.access = { viewer: await access(viewer), operator: await access(operator),
                    surrogate: await access(surrogate) };

  for (const [session, client] of [[surrogate, sClient], [viewer, vClient], [operator, opClient]]) {
    await session.close();
    await client.disconnect();
  }
  console.log("RESULT " + JSON.stringify(result));
}

main().catch((err) => { console.error(err); process.exit(1); });
