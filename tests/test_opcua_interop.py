"""Interoperability: node-opcua drives our server over Basic256Sha256 SignAndEncrypt.

node-opcua is a prerequisite that ``make test`` installs into
``out/.node_opcua`` (tools/install_test_prereqs.sh). Without it the test is
skipped, saying why, and under ``make test`` it fails.
"""

import asyncio
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from opcua_server.harness import ServerProcess, connect, prepare_state
from opcua_server.security import APPLICATION_URI_CLIENT

NODE_OPCUA_VERSION = "2.186.4"
ROOT = Path(__file__).resolve().parents[1]
INSTALL_DIR = ROOT / "out" / ".node_opcua"
SCRIPT = Path(__file__).with_name("interop") / "node_opcua_client.js"


@pytest.fixture(scope="module")
def node_opcua():
    node = shutil.which("node")
    marker = INSTALL_DIR / "node_modules" / "node-opcua" / "package.json"
    installed = marker.exists() and json.loads(marker.read_text())["version"] == NODE_OPCUA_VERSION
    if not node or not installed:
        message = (f"node-opcua {NODE_OPCUA_VERSION} is not installed in {INSTALL_DIR}: "
                   "run 'make test-prereqs' (needs node and npm)")
        if os.environ.get("MINETWIN_REQUIRE_PREREQS") == "1":
            pytest.fail(message)
        pytest.skip(message)
    return node


@pytest.mark.slow
def test_node_opcua_browses_reads_subscribes_and_writes_by_role(node_opcua, tmp_path):
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    state = prepare_state(tmp_path / "state")
    cert_pem = tmp_path / "client_cert.pem"
    cert_pem.write_bytes(x509.load_der_x509_certificate(state["client_cert"].read_bytes())
                         .public_bytes(Encoding.PEM))
    server = ServerProcess(tmp_path, state, speed=10.0)
    try:
        async def namespace_index():
            client = await connect(server.url, state, "viewer")
            try:
                return await client.get_namespace_index("urn:minetwin:mock800xa")
            finally:
                await client.disconnect()

        config = tmp_path / "interop.json"
        config.write_text(json.dumps({
            "url": server.url, "workdir": str(tmp_path), "application_uri": APPLICATION_URI_CLIENT,
            "certificate_pem": str(cert_pem), "private_key_pem": str(state["client_key"]),
            "namespace_index": asyncio.run(namespace_index()), "listen_ms": 3000,
            "operator_password": state["passwords"]["operator"],
            "viewer_password": state["passwords"]["viewer"]}))
        run = subprocess.run([node_opcua, str(SCRIPT), str(config)], capture_output=True, text=True,
                             timeout=120, env={"NODE_PATH": str(INSTALL_DIR / "node_modules"),
                                               "PATH": "/usr/bin:/bin"})
    finally:
        server.stop()
    assert run.returncode == 0, run.stderr[-3000:]
    lines = [line for line in run.stdout.splitlines() if line.startswith("RESULT ")]
    assert lines, run.stdout[-3000:]
    result = json.loads(lines[-1].removeprefix("RESULT "))
    assert {"CV101", "SP201", "CV301", "SimulationTime", "AdvanceTime"} <= set(result["browse"])
    assert len(result["bin_tracking_ids"]) == len(result["bin_masses"]) == 20
    assert any(m > 0 for m in result["bin_masses"])
    sequences = [e["sequence"] for e in result["events"]]
    assert len(sequences) >= 10  # ~1 bin per simulated second at speed 10 for 3 s
    assert sequences == list(range(sequences[0], sequences[0] + len(sequences)))
    assert all(e["mass"] == pytest.approx(250.0) for e in result["events"])
    assert result["operator_write"] == "Good"
    assert result["operator_write_out_of_range"] == "BadOutOfRange"
    assert result["viewer_write"] == "BadUserAccessDenied"
    assert result["setpoint_after"] == pytest.approx(321.0)
