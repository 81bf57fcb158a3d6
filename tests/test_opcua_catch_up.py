"""A stockpile client far behind the plant catches up in bounded slices and stops
promptly, losing nothing (issue 18, "Throughput and lag").

Before: each cycle caught the whole backlog up in one blocking ``advance_to``
(one sub-step and one storage step per bin), the session dropped and a
SIGTERM during the catch-up was taken after minutes. Now a FIFO pile is
stepped one slice of plant time at a time, each slice's bins received
together, and a cycle's stepping stops after ``cycle_budget_s`` of wall time.
No assertion here is on speed: the slices must give the same outflow as
stepping to each bin, no step may exceed the slice, and a stop during the
catch-up must come within a bound and leave the exchange whole.
"""

import json
import signal
import time
import urllib.request

import numpy as np
import pytest

from opcua_server.audit import audit
from minetwin.harness import ServerProcess, StockpileProcess, drain_and_stop, prepare_state
from surrogate.client import ClientOptions, StockpileClient

SLICE_S = 5.0
"""The client's default ``slice_s`` [s of plant time]."""
STOP_BOUND_S = 5.0
"""Wall time [s] within which a stopped client must have exited (checkpoint and
summary written); it took 241 s during a catch-up before (measured)."""


def _client_with_backlog(batch: bool) -> StockpileClient:
    """A client with 400 bins read from the plant and not applied, and a feeder
    that starts late, speeds up past the inflow (the pile runs empty) and slows."""
    client = StockpileClient(ClientOptions(server_url="opc.tcp://127.0.0.1:1/", model="fifo"))
    client.asset.storage.arrivals_join_the_tail = batch  # False: to each bin in turn
    rng = np.random.default_rng(3)
    times = np.cumsum(rng.uniform(0.2, 0.8, 400))  # ~450 kg/s in
    for k, t in enumerate(times, start=1):
        client.inbox[k] = {"sequence": k, "tracking_id": 1000 + k,
                           "mass": float(rng.uniform(50.0, 400.0)),
                           "grade": float(rng.uniform(0.0, 0.02)), "hardness": 1.0,
                           "source": k % 2, "time": float(t)}
    client.server_last_sequence = times.size
    client.setpoint_changes = [(0.0, 0.0), (10.0, 300.0), (60.0, 1200.0), (100.0, 300.0)]
    return client


def _outflow(client: StockpileClient) -> dict:
    out = {}
    # cycles shorter than a slice, then longer ones (a backlog)
    for target in [*np.arange(3.7, 60.0, 3.7), 80.0, 110.0, 150.0, 230.0]:
        report = client.advance_to(float(target))
        for tid, mass in zip(report["tracking_ids"] if report else [],
                             report["masses"] if report else []):
            out[tid] = out.get(tid, 0.0) + mass
    return out


def test_slices_take_exactly_what_stepping_to_each_bin_takes():
    sliced, stepped = _client_with_backlog(True), _client_with_backlog(False)
    out_sliced, out_stepped = _outflow(sliced), _outflow(stepped)
    assert sliced.state.last_applied == stepped.state.last_applied == 400
    assert sliced.asset.time == pytest.approx(stepped.asset.time)
    assert sorted(out_sliced) == sorted(out_stepped) and out_sliced
    for tid, mass in out_stepped.items():
        assert out_sliced[tid] == pytest.approx(mass, rel=1e-12)
    assert sliced.asset.held_by_tracking_id() == pytest.approx(stepped.asset.held_by_tracking_id())
    # fewer, longer steps where exact, none longer than the slice
    assert stepped.largest_step_s <= 0.5 + 1e-9
    assert 0.5 < sliced.largest_step_s <= SLICE_S + 1e-9
    assert len(sliced.asset.history()) < len(stepped.asset.history()) / 3


def _client_filling_from_empty(batch: bool) -> StockpileClient:
    """The 1,000 bins/s benchmark's plant: an empty pile, 2.5 kg bins 0.01 s apart
    (250 kg/s) and the feeder at 200 kg/s from the start, 3,000 bins read."""
    client = StockpileClient(ClientOptions(server_url="opc.tcp://127.0.0.1:1/", model="fifo"))
    client.asset.storage.arrivals_join_the_tail = batch
    for k in range(1, 3001):
        client.inbox[k] = {"sequence": k, "tracking_id": k, "mass": 2.5, "grade": 0.01,
                           "hardness": 1.0, "source": k % 2, "time": 0.01 * k}
    client.server_last_sequence = 3000
    client.asset.set_discharge_rate(200.0)
    return client


def test_a_pile_filling_from_empty_catches_up_in_slices_that_grow_with_it():
    """Before, a pile smaller than one slice's outflow (200 kg/s x 5 s) was stepped
    to each bin: 2,000 bins one by one here, and 65 s of plant time behind at
    1,000 bins/s (measured). Now its slices end before the feeder's credit reaches
    the mass held, and the outflow is still exactly the per-bin one."""
    sliced, stepped = _client_filling_from_empty(True), _client_filling_from_empty(False)
    out_sliced, out_stepped = {}, {}
    for client, out in ((sliced, out_sliced), (stepped, out_stepped)):
        for target in (15.0, 30.0):  # far behind: cycles longer than a slice
            report = client.advance_to(float(target))
            for tid, mass in zip(report["tracking_ids"], report["masses"]):
                out[tid] = out.get(tid, 0.0) + mass
    assert sliced.state.last_applied == stepped.state.last_applied == 3000
    assert sorted(out_sliced) == sorted(out_stepped) and out_sliced
    for tid, mass in out_stepped.items():
        assert out_sliced[tid] == pytest.approx(mass, rel=1e-12)
    assert sliced.asset.held_by_tracking_id() == pytest.approx(stepped.asset.held_by_tracking_id())
    assert len(stepped.asset.history()) >= 3000
    assert len(sliced.asset.history()) < 300, len(sliced.asset.history())
    # what the client writes to HeldMass and AverageGrade: the pile's totals, exactly
    totals = sliced.asset.totals()
    assert sliced._held_mass_and_grade() == (totals["held_mass_kg"], totals["grade"])


def _stockpile_time(url: str) -> float | None:
    try:
        with urllib.request.urlopen(url + "/totals", timeout=2) as resp:
            return json.loads(resp.read())["time_s"]
    except (OSError, ValueError, KeyError):
        return None


def test_a_client_far_behind_stops_promptly_on_sigterm_and_loses_nothing(tmp_path):
    state = prepare_state(tmp_path / "state")
    until = 3000.0  # 3,000 bins discharged before the stockpile starts
    server = ServerProcess(tmp_path, state, speed=1000.0, until=until)
    stockpile = None
    try:
        while not server.clock_frozen():
            time.sleep(0.2)
        # a small stepping budget: the catch-up takes several seconds of cycles
        stockpile = StockpileProcess(tmp_path, state, server.url, rest=True,
                                     extra=["--cycle-budget", "0.02"])
        while not (_stockpile_time(stockpile.rest_url) or 0.0) > 0.0:
            time.sleep(0.05)
        stopped = time.monotonic()
        stockpile.proc.send_signal(signal.SIGTERM)
        code = stockpile.proc.wait(60)
        took = time.monotonic() - stopped
        assert code == 0
        assert took < STOP_BOUND_S, f"the stop took {took:.1f} s"
        first = json.loads(stockpile.summary.read_text())
        assert 0.0 < first["time_s"] < until  # stopped during the catch-up
        assert first["largest_step_s"] <= SLICE_S + 1e-9
        stockpile.stop()
        # restarted from its checkpoint, it catches the rest up
        stockpile = StockpileProcess(tmp_path, state, server.url, rest=True)
        ledger, summary = drain_and_stop(server, stockpile, timeout=60)
    finally:
        for proc in (stockpile, server):
            if proc is not None:
                proc.stop()
    result = audit(ledger, summary)
    assert result["bins_in"] > 1000
    assert result["tracking_ids_lost"] == 0 and result["tracking_ids_duplicated"] == 0
    assert result["mass_balance_rel_error"] < 1e-9
    assert result["pending_unacknowledged"] == 0 and result["unsent_reports"] == 0
    assert summary["time_s"] == pytest.approx(until)
    assert summary["largest_step_s"] <= SLICE_S + 1e-9
    assert summary["reconnects"] == 0  # the session lived through the catch-up
