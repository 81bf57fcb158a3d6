// The node-opcua client of the interoperability scripts: Basic256Sha256
// SignAndEncrypt with the test's client certificate, its own PKI folder under
// cfg.workdir, at most 2 reconnection attempts. `options` override any setting.
const path = require("path");
const {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, OPCUACertificateManager,
} = require("node-opcua");

async function secureClient(cfg, applicationName, options = {}) {
  const certificateManager = new OPCUACertificateManager({
    rootFolder: path.join(cfg.workdir, "node_pki"),
    automaticallyAcceptUnknownCertificate: true,
  });
  await certificateManager.initialize();
  return OPCUAClient.create({
    applicationName,
    applicationUri: cfg.application_uri,
    securityMode: MessageSecurityMode.SignAndEncrypt,
    securityPolicy: SecurityPolicy.Basic256Sha256,
    certificateFile: cfg.certificate_pem,
    privateKeyFile: cfg.private_key_pem,
    clientCertificateManager: certificateManager,
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 2, initialDelay: 300, maxDelay: 1000 },
    ...options,
  });
}

module.exports = { secureClient };
