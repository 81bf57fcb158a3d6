"""The mock 800xA's durable ledger (``opcua_server.ledger_store``) written
incrementally: a save writes the rows of what changed and a small state, never
the whole belts, and a plant reopened from the file is the same plant, bin for
bin on both belts."""

import json
import sqlite3

import numpy as np
import pytest

from cosim.errors import ValidationError

from opcua_server.config import load_config
from opcua_server.ledger_store import LedgerStore
from opcua_server.process import PlantProcess


def _belts(process):
    out = {}
    for name in ("cv101", "cv301"):
        belt = getattr(process, name)
        out[name] = {key: getattr(belt, key).tolist()
                     for key in ("tracking_id", "mass", "grade", "hardness", "source")}
        out[name]["offset_m"], out[name]["shifts_done"] = belt.offset_m, belt.shifts_done
    out["cv301_contents"] = [list(c.items()) for c in process.cv301_contents]
    return out


def _report_some(process, sequence, rng):
    """Report outflow of a few discharged bins, some reported twice with other grades
    (a CV301 slot's grade is the latest report's)."""
    candidates = [r.tracking_id for r in process.pending]
    tids = rng.choice(candidates, size=min(5, len(candidates)), replace=False)
    masses = [1.0 + k for k in range(len(tids))]
    grades = rng.uniform(0.0, 0.05, size=len(tids)).tolist()
    return process.report_outflow(sequence, tids.tolist(), masses, grades)


def test_a_reopened_ledger_is_the_same_plant_bin_for_bin_on_both_belts(tmp_path):
    config = load_config(overrides={"cv101": {"bin_length_m": 0.2}})  # 200 bins on CV101
    plant = PlantProcess(config)
    store = LedgerStore(tmp_path / "ledger.sqlite")
    rng = np.random.default_rng(3)
    sequence = 0
    for k in range(60):  # saves between belt shifts, reports between and across shifts
        plant.advance(0.7)
        if plant.pending and k % 2:
            sequence += 1
            assert _report_some(plant, sequence, rng) == "applied"
        if k % 3 == 0:
            store.save(plant, force=True)
    plant.set_belt_speed("cv301", 3.0)
    plant.acknowledge(plant.last_sequence // 2)
    store.save(plant, force=True)
    assert any(plant.cv301_contents[1:]) and plant.cv101.mass.sum() > 0  # loaded belts
    store.close()

    again = PlantProcess(config)
    reopened = LedgerStore(tmp_path / "ledger.sqlite")
    assert reopened.load(again)
    assert _belts(again) == _belts(plant)  # exactly: same sums in the same order
    assert again.state() == plant.state() and again.ledger() == plant.ledger()
    # both go on identically: discharges, deliveries, CV301's contents
    for k in range(40):
        records = [(r.sequence, r.tracking_id, r.mass_kg) for r in plant.advance(0.9)]
        assert [(r.sequence, r.tracking_id, r.mass_kg) for r in again.advance(0.9)] == records
        if k % 2:
            sequence += 1
            assert _report_some(plant, sequence, np.random.default_rng(k)) == \
                _report_some(again, sequence, np.random.default_rng(k))
    assert _belts(again) == _belts(plant) and again.ledger() == plant.ledger()


def test_a_save_writes_what_changed_not_the_whole_belts(tmp_path):
    """With 2,000 bins on CV101 (the 1,000 bins/s benchmark's plant) the saved state
    stays a few hundred bytes, and the belts' rows are deleted once the bins left."""
    config = load_config(overrides={"cv101": {"bin_length_m": 0.02}})
    plant = PlantProcess(config)
    store = LedgerStore(tmp_path / "ledger.sqlite")
    for _ in range(50):
        plant.advance(1.0)
        store.save(plant)
    assert plant.cv101.n_bins == 2000 and plant.last_sequence > 2000
    (state,) = store.db.execute("SELECT value FROM meta WHERE key = 'state'").fetchone()
    assert len(state) < 1000, len(state)
    assert "tracking_id" not in json.loads(state)["cv101"]
    (rows,) = store.db.execute("SELECT count(*) FROM cv101_loads").fetchone()
    assert rows == plant.cv101.n_bins  # the bins on the belt, none of those discharged
    (inbound,) = store.db.execute("SELECT count(*) FROM inbound").fetchone()
    assert inbound == plant.last_sequence


def test_a_ledger_of_another_schema_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "ledger.sqlite"
    with sqlite3.connect(path) as db:  # a schema-1 file: both belts as JSON in the state
        db.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
        db.executemany("INSERT INTO meta VALUES (?, ?)", [("ledger_id", "x"), ("schema", "1")])
    with pytest.raises(ValidationError, match=f"ledger: .*schema 2.*{path} has schema 1"):
        LedgerStore(path)
