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
from asyncua import ua

from minetwin.harness import ServerProcess, connect, prepare_state
from opcua_server.process import MAX_REPORT_ROWS
from opcua_protocol import APPLICATION_URI_CLIENT

NODE_OPCUA_VERSION = "2.186.4"
ROOT = Path(__file__).resolve().parents[1]
INSTALL_DIR = ROOT / "out" / ".node_opcua"
INTEROP = Path(__file__).with_name("interop")
SCRIPT = INTEROP / "node_opcua_client.js"


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


def _pem_certificate(state, tmp_path) -> Path:
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    cert_pem = tmp_path / "client_cert.pem"
    cert_pem.write_bytes(x509.load_der_x509_certificate(state["client_cert"].read_bytes())
                         .public_bytes(Encoding.PEM))
    return cert_pem


def _run_node(node, script, config: dict, tmp_path) -> dict:
    path = tmp_path / f"{script.stem}.json"
    path.write_text(json.dumps(config))
    run = subprocess.run([node, str(script), str(path)], capture_output=True, text=True,
                         timeout=120, env={"NODE_PATH": str(INSTALL_DIR / "node_modules"),
                                           "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr[-3000:]
    lines = [line for line in run.stdout.splitlines() if line.startswith("RESULT ")]
    assert lines, run.stdout[-3000:]
    return json.loads(lines[-1].removeprefix("RESULT "))


async def _namespace_index(url, state):
    client = await connect(url, state, "viewer")
    try:
        return await client.get_namespace_index("urn:minetwin:mock800xa")
    finally:
        await client.disconnect()


@pytest.mark.slow
def test_node_opcua_browses_reads_subscribes_and_writes_by_role(node_opcua, tmp_path):
    state = prepare_state(tmp_path / "state")
    cert_pem = _pem_certificate(state, tmp_path)
    server = ServerProcess(tmp_path, state, speed=10.0)
    try:
        result = _run_node(node_opcua, SCRIPT, {
            "url": server.url, "workdir": str(tmp_path), "application_uri": APPLICATION_URI_CLIENT,
            "certificate_pem": str(cert_pem), "private_key_pem": str(state["client_key"]),
            "namespace_index": asyncio.run(_namespace_index(server.url, state)), "listen_ms": 3000,
            "operator_password": state["passwords"]["operator"],
            "viewer_password": state["passwords"]["viewer"]}, tmp_path)
    finally:
        server.stop()
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


@pytest.mark.slow
def test_node_opcua_gets_the_right_status_for_each_security_defect_of_issue_18(node_opcua,
                                                                                 tmp_path):
    """Identity per session, the None channel, subscription ownership, type
    checks, the replay conflict, argument counts, access attributes, the array
    bound, as node-opcua sees them (the asyncua versions: test_opcua_security)."""
    state = prepare_state(tmp_path / "state")
    server = ServerProcess(tmp_path, state, lockstep=True)
    try:
        async def advance():  # bins reach the stockpile, so tracking ids are known
            client = await connect(server.url, state, "surrogate")
            try:
                idx = await client.get_namespace_index("urn:minetwin:mock800xa")
                await client.get_node(ua.NodeId("Plant", idx)).call_method(
                    ua.NodeId("Plant.AdvanceTime", idx), ua.Variant(60.0, ua.VariantType.Double))
                return idx
            finally:
                await client.disconnect()

        result = _run_node(node_opcua, INTEROP / "node_opcua_security.js", {
            "url": server.url, "workdir": str(tmp_path), "application_uri": APPLICATION_URI_CLIENT,
            "certificate_pem": str(_pem_certificate(state, tmp_path)),
            "private_key_pem": str(state["client_key"]), "namespace_index": asyncio.run(advance()),
            "passwords": state["passwords"], "max_report_rows": MAX_REPORT_ROWS}, tmp_path)
    finally:
        server.stop()
    assert result["second_session"] == "BadTooManySessions"
    assert result["none_discovery"] == 3 and result["none_session"] == "BadSecurityModeRejected"
    assert result["viewer_delete_subscription"] == ["BadSubscriptionIdInvalid"]
    assert result["operator_write"] == "Good" and result["operator_notified_after"] >= 1
    assert result["typed_writes"] == ["BadTypeMismatch"] * 3
    assert result["setpoint_after"] == pytest.approx(333.0)
    assert result["wrong_types"]["status"] == "BadTypeMismatch"
    assert result["wrong_types"]["inputs"] == ["Good"] + ["BadTypeMismatch"] * 3
    assert result["missing"]["status"] == "BadArgumentsMissing"
    assert result["too_many"]["status"] == "BadTooManyArguments"
    assert result["applied"] == {"status": "Good", "inputs": ["Good"] * 4, "message": "applied"}
    assert result["resent"]["message"] == "already applied"
    assert result["conflict"]["status"] == "BadSequenceNumberInvalid"
    assert "applied with other contents" in result["conflict"]["message"]
    assert result["too_long"]["status"] == "BadTooManyOperations"
    assert not any("np." in str(r.get("message")) for r in result.values() if isinstance(r, dict))
    read, write = 1, 3
    assert result["access"] == {
        "viewer": {"setpoint": read, "held_mass": read, "report_executable": False},
        "operator": {"setpoint": write, "held_mass": read, "report_executable": False},
        "surrogate": {"setpoint": read, "held_mass": write, "report_executable": True}}
