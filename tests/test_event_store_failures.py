"""The event store under another process's lock, and a store that fails mid-run.

A second process holds an exclusive SQLite lock on a running simulation's
events.sqlite: a short hold is waited out and the run completes; a hold longer
than ``simulation.event_store_timeout_s`` fails the run with a message that
blames the store, not an asset, and every other output is still written.
"""

import json
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from cosim.events import EventStore
from cosim.master import CosimulationError
from cosim.scenario import load, run_scenario

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "step_response.toml"

HOLD_LOCK = """
import sqlite3, sys, time
db = sqlite3.connect(sys.argv[1], timeout=0, isolation_level=None)
db.execute("BEGIN EXCLUSIVE")
print("locked", flush=True)
time.sleep(float(sys.argv[2]))
db.execute("COMMIT")
"""


def _lock_during_run(hold_s: float, timeout_s: float, out):
    config = load(EXAMPLE)
    config["simulation"]["event_store_timeout_s"] = timeout_s
    holders = []

    def lock(simulation):
        simulation.plant.flush_events()
        holder = subprocess.Popen([sys.executable, "-c", HOLD_LOCK,
                                   str(simulation.plant.events.path), str(hold_s)],
                                  stdout=subprocess.PIPE, text=True)
        assert holder.stdout.readline().strip() == "locked"
        holders.append(holder)

    try:
        return run_scenario(config, out, until=120.0, before_run=lock)
    finally:
        for holder in holders:
            holder.wait(timeout=60)


def test_a_lock_shorter_than_the_timeout_is_waited_out(tmp_path):
    started = time.monotonic()
    _, summary = _lock_during_run(hold_s=1.0, timeout_s=30.0, out=tmp_path)
    assert summary["failed"] is None
    assert time.monotonic() - started >= 1.0
    with EventStore(tmp_path / "events.sqlite", readonly=True) as store:
        assert len(store.events(type="appear")) > 0


def test_a_lock_past_the_timeout_blames_the_store_and_keeps_the_other_outputs(tmp_path):
    with pytest.raises(CosimulationError) as failure:
        _lock_during_run(hold_s=6.0, timeout_s=0.5, out=tmp_path)
    message = str(failure.value)
    assert "event store" in message and "events.sqlite" in message and "locked" in message
    assert "truck" not in message and "failed at t" not in message
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["failed"] == message
    assert len(pd.read_parquet(tmp_path / "timeseries.parquet")) > 0
    assert (tmp_path / "overview.png").is_file()


def test_ids_beyond_sqlites_integers_are_refused_not_wrapped():
    import numpy as np

    from cosim.errors import ValidationError

    store = EventStore(":memory:")
    batch = {"id": np.array([2 ** 63], dtype=np.uint64), "mass": np.ones(1),
             "position": np.zeros((1, 3)), "grade": np.ones(1), "hardness": np.ones(1),
             "origin_block": np.zeros(1, int), "f": np.full((1, 16), 1 / 16)}
    with pytest.raises(ValidationError, match=r"id: must be in \[0, 9223372036854775807\]"):
        store.record_batch("appear", "source", 0.0, batch)
    assert store.events().empty
