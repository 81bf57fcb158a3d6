"""The plugin's OPC UA fixtures: a real mock 800xA server process in lockstep, the real
stockpile client, SignAndEncrypt with test credentials. Each server start costs ~5-10 s.
(A clean lockstep run passing the mass and id checks is the example folder's test,
run by tests/test_testing_examples.py.)"""

import json
from concurrent.futures import ThreadPoolExecutor

import pytest

from minetwin.testing.opcua import LockstepStockpile, MockPlantServer
from surrogate.client import StockpileClient

UNTIL_S = 60.0


class DropsOneRecord(StockpileClient):
    """Test double: a client whose exchange silently drops one tracking id's record
    from its third outflow report (the report's sequence stays intact, so the
    server's gap detection cannot notice; only an audit of mass and ids can)."""

    dropped = None
    reports = 0

    def advance_to(self, target_time, budget_s=None):
        report = super().advance_to(target_time, budget_s)
        if report is not None:
            self.reports += 1
            if self.reports == 3:
                self.dropped = (report["tracking_ids"].pop(0), report["masses"].pop(0))
                report["grades"].pop(0)
        return report


def test_a_lossy_exchange_is_caught_with_the_lost_ids(mock_800xa, stockpile_client):
    client = stockpile_client(model="fifo", period=2.0, client_class=DropsOneRecord)
    result = client.run(until=UNTIL_S)
    assert client.client.dropped is not None, "the test double never dropped a record"
    tracking_id, mass = client.client.dropped
    with pytest.raises(AssertionError) as balance:
        result.assert_mass_balance()
    assert f"{mass:.6g} kg lost" in str(balance.value)
    with pytest.raises(AssertionError) as ids:
        result.assert_ids_accounted()
    message = str(ids.value)
    assert message.startswith("the OPC UA stockpile exchange: of ")
    # the id left whole in that report (lost) or partly in a neighbouring one (partly lost)
    assert (f"1 tracking id(s) lost (entered, but neither held nor left): {tracking_id}."
            in message) or f"partly lost (mass missing): {tracking_id}: {mass:.6g} kg" in message


def _lockstep_run(folder):
    server = MockPlantServer(folder).start()
    try:
        return LockstepStockpile(server, "mixing", seed=7, period=2.0).run(UNTIL_S).fingerprint()
    finally:
        server.stop()


def test_the_same_lockstep_run_gives_identical_results_twice(tmp_path):
    # two independent server processes and clients, side by side (each its own event loop)
    with ThreadPoolExecutor(max_workers=2) as pool:
        outcomes = list(pool.map(_lockstep_run, [tmp_path / "first", tmp_path / "second"]))
    first = json.loads(outcomes[0])
    assert first["left"] and first["held"] and len(first["history"]) >= UNTIL_S / 0.5
    assert outcomes[0] == outcomes[1]
