"""Lockstep: the stockpile drives the server's clock; two runs give the same result.

Server (``--lockstep``) and client (``--lockstep --period 1 --duration 60``)
are real processes; the plant only advances when the client calls
``Plant.AdvanceTime``, so the run does not depend on the wall clock.
"""

import json
import threading

import pytest

from opcua_server.audit import audit
from minetwin.harness import ServerProcess, StockpileProcess, prepare_state


def _run(workdir, state, results, key):
    server = ServerProcess(workdir, state, lockstep=True)
    client = None
    try:
        client = StockpileProcess(workdir, state, server.url, model="mixing", lockstep=True,
                                  period=1.0, duration=60.0)
        client.proc.wait(120)
        results[key] = client.proc.returncode
    finally:
        if client is not None:
            client.stop()
        server.stop()
    results[key] = (results[key], json.loads(server.ledger.read_text()),
                    json.loads(client.summary.read_text()))


@pytest.mark.slow
def test_lockstep_runs_are_identical_and_lose_nothing(tmp_path):
    results = {}
    runs = []
    for k in range(2):  # both runs at once: independent servers and clients
        workdir = tmp_path / f"run{k}"
        workdir.mkdir()
        state = prepare_state(workdir / "state")
        runs.append(threading.Thread(target=_run, args=(workdir, state, results, k)))
    for thread in runs:
        thread.start()
    for thread in runs:
        thread.join(180)
    (code_a, ledger_a, summary_a), (code_b, ledger_b, summary_b) = results[0], results[1]
    assert code_a == code_b == 0
    assert ledger_a["time_s"] == pytest.approx(60.0) and summary_a["time_s"] == pytest.approx(60.0)
    for ledger, summary in ((ledger_a, summary_a), (ledger_b, summary_b)):
        result = audit(ledger, summary)
        assert result["bins_in"] >= 35 and result["mass_out_kg"] > 0
        assert result["tracking_ids_lost"] == result["tracking_ids_duplicated"] == 0
        assert result["mass_balance_rel_error"] < 1e-9
        assert ledger["pending"] == 0 and summary["outbox"] == 0
    assert ledger_a["left"] == ledger_b["left"]
    assert ledger_a["outflow_log"] == ledger_b["outflow_log"]
    assert summary_a["held"] == summary_b["held"]
