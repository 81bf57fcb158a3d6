"""A stockpile client far behind the plant keeps the feeder's invariants.

Issue 14 saw, under CPU load, a stockpile that lagged 9 s discharge 11.25 t
where a 200 kg/s feeder could deliver at most 10.7 t in the plant time since
its scheduled start: the client applied the setpoint it read to the whole
interval it caught up, including the time before the setpoint took effect.
The plant now publishes the plant time of each setpoint change
(``SP201.SetpointChangeTimes`` / ``SetpointChangeValues``) and the client
applies each from then.

These tests make the lag on purpose (the client starts 25 s of plant time
late) instead of hoping for a loaded machine, and assert the invariants:
nothing discharged before the scheduled start, never more than the integral
of the setpoint over plant time (plus one particle), nothing lost.
"""

import asyncio
import time

import pytest
from asyncua import ua

from opcua_server.audit import audit
from minetwin.harness import ServerProcess, StockpileProcess, connect, drain_and_stop, \
    prepare_state
from surrogate.client import ClientOptions, StockpileClient

SETPOINT_KG_S = 200.0
START_S = 30.0
PARTICLE_MASS_KG = 100.0


def test_a_lagging_client_applies_each_setpoint_from_its_plant_time():
    client = StockpileClient(ClientOptions(server_url="opc.tcp://127.0.0.1:1/", model="fifo"))
    for k in range(10):  # 2.5 t in the pile before the feeder starts
        client.asset.time = float(k)
        client.asset.receive_bin(k + 1, 250.0, 0.01, 1.0)
    client.asset.set_discharge_rate(SETPOINT_KG_S)  # what the client read at plant time 45 s
    client.setpoint_changes = [(0.0, 0.0), (START_S, SETPOINT_KG_S)]
    history_before = len(client.asset.history())
    report = client.advance_to(40.0)
    rows = client.asset.history()[history_before:]
    held_at_start = [r["held_mass_kg"] for r in rows if r["time_s"] <= START_S + 1e-9]
    assert held_at_start and min(held_at_start) == pytest.approx(2500.0)  # nothing before 30 s
    assert sum(report["masses"]) <= SETPOINT_KG_S * (40.0 - START_S) + PARTICLE_MASS_KG
    assert sum(report["masses"]) >= SETPOINT_KG_S * (40.0 - START_S) - PARTICLE_MASS_KG


@pytest.mark.slow
def test_a_client_started_late_discharges_no_more_than_the_setpoint_over_plant_time(tmp_path):
    config = tmp_path / "plant.toml"
    config.write_text(f"[sp201]\ndischarge_start_s = {START_S}\n")
    state = prepare_state(tmp_path / "state")
    duration = 60.0
    server = ServerProcess(tmp_path, state, speed=10.0, config=config, until=duration)
    stockpile = None
    try:
        async def plant_time():
            client = await connect(server.url, state, "viewer")
            try:
                idx = await client.get_namespace_index("urn:minetwin:mock800xa")
                return await client.get_node(ua.NodeId("Plant.SimulationTime", idx)).read_value()
            finally:
                await client.disconnect()

        while asyncio.run(plant_time()) < START_S + 15:  # the client starts 15 s into the feed
            time.sleep(0.2)
        stockpile = StockpileProcess(tmp_path, state, server.url, model="fifo", rest=True)
        ledger, summary = drain_and_stop(server, stockpile, timeout=60)
    finally:
        for proc in (stockpile, server):
            if proc is not None:
                proc.stop()
    result = audit(ledger, summary)
    assert ledger["time_s"] == pytest.approx(duration)  # the clock froze at --until
    assert result["tracking_ids_lost"] == 0 and result["tracking_ids_duplicated"] == 0
    assert result["mass_balance_rel_error"] < 1e-9 and result["unsent_reports"] == 0
    held = [(r["time_s"], r["held_mass_kg"]) for r in summary["history"]]
    before = [m for t, m in held if t <= START_S]
    assert before == sorted(before)  # the pile only filled before the feeder's start
    assert 0 < result["mass_out_kg"] <= SETPOINT_KG_S * (duration - START_S) + PARTICLE_MASS_KG
