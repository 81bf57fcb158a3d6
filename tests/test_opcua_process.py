"""Plant process and stockpile asset without the network: bins, ledger, refusals."""

import copy
import math

import numpy as np
import pytest

from cosim.errors import ValidationError
from opcua_server.audit import audit
from opcua_protocol import load_nodemap
from opcua_server.config import load_config, source_names
from opcua_server.process import ExchangeRefused, PlantProcess
from surrogate.stockpile import StockpileAsset


@pytest.fixture
def plant():
    process = PlantProcess(load_config())
    process.advance(60.0)  # CV101 is 40 m at 2 m/s: bins start arriving after 20 s
    return process


def test_belt_discharges_one_bin_per_bin_length_with_schedule_mass(plant):
    config = load_config()
    speed, length = config["cv101"]["belt_speed_m_s"], config["cv101"]["bin_length_m"]
    records = plant.pending
    assert plant.last_sequence == len(records) > 0
    assert [r.sequence for r in records] == list(range(1, len(records) + 1))
    lot = config["feed"]["lots"][0]
    assert all(math.isclose(r.mass_kg, lot["feed_rate_kg_s"] * length / speed) for r in records)
    # bins are discharged after travelling the belt: one per bin_length / speed seconds
    times = np.array([r.time_s for r in records])
    assert np.allclose(np.diff(times), length / speed)
    assert len({r.tracking_id for r in records}) == len(records)


def test_feed_schedule_alternates_sources_and_steps_hardness():
    process = PlantProcess(load_config())
    process.advance(200.0)
    sources = [r.source for r in process.pending]
    hardness = [r.hardness for r in process.pending]
    assert set(sources) == {0, 1}
    assert sorted(set(hardness)) == [1.0, 1.3, 1.8]


def test_acknowledge_drops_pending_and_is_idempotent(plant):
    n = plant.last_sequence
    assert plant.acknowledge(3) == 3
    assert [r.sequence for r in plant.pending][0] == 4
    assert plant.acknowledge(2) == 3  # an older number changes nothing
    with pytest.raises(ExchangeRefused) as err:
        plant.acknowledge(n + 1)
    assert err.value.status == "BadOutOfRange" and "sequence" in err.value.message
    assert plant.acknowledged_sequence == 3


def _state(process):
    return copy.deepcopy((process.outbound_sequence, process.left_mass, process.loading_contents))


@pytest.mark.parametrize("case, status, field", [
    ({"masses": [-1.0]}, "BadOutOfRange", "masses"),
    ({"masses": [float("nan")]}, "BadOutOfRange", "masses"),
    ({"masses": [float("inf")]}, "BadOutOfRange", "masses"),
    ({"grades": [1.5]}, "BadOutOfRange", "grades"),
    ({"grades": [float("nan")]}, "BadOutOfRange", "grades"),
    ({"tracking_ids": [999_999]}, "BadInvalidArgument", "tracking_ids"),
    ({"masses": [1e9]}, "BadOutOfRange", "masses"),
    ({"masses": [1.0, 2.0]}, "BadInvalidArgument", "masses"),
    ({"sequence": 5}, "BadSequenceNumberInvalid", "sequence"),
])
def test_bad_outflow_is_refused_and_changes_nothing(plant, case, status, field):
    tid = plant.pending[0].tracking_id
    report = {"sequence": 1, "tracking_ids": [tid], "masses": [10.0], "grades": [0.01]}
    report.update(case)
    before = _state(plant)
    with pytest.raises(ExchangeRefused) as err:
        plant.report_outflow(**report)
    assert err.value.status == status
    assert err.value.message.startswith(field + ":")
    assert _state(plant) == before
    # the exchange goes on: a good report is applied afterwards
    assert plant.report_outflow(1, [tid], [10.0], [0.01]) == "applied"


def test_outflow_applied_once_and_over_delivery_refused(plant):
    record = plant.pending[0]
    half = record.mass_kg / 2
    assert plant.report_outflow(1, [record.tracking_id], [half], [0.01]) == "applied"
    assert plant.report_outflow(1, [record.tracking_id], [half], [0.01]) == "already applied"
    assert plant.left_mass[record.tracking_id] == half
    assert plant.duplicate_reports == 1
    with pytest.raises(ExchangeRefused):
        plant.report_outflow(2, [record.tracking_id], [half * 1.001], [0.01])
    assert plant.report_outflow(2, [record.tracking_id], [half], [0.01]) == "applied"


def test_setpoint_and_belt_speed_ranges(plant):
    for bad in (-1.0, 2000.1, float("nan"), float("inf")):
        with pytest.raises(ExchangeRefused) as err:
            plant.set_discharge_rate(bad)
        assert err.value.status == "BadOutOfRange"
        assert "DischargeRateSetpoint" in err.value.message
    assert plant.discharge_rate_setpoint == load_config()["sp201"]["discharge_rate_kg_s"]
    plant.set_discharge_rate(2000.0)
    with pytest.raises(ExchangeRefused):
        plant.set_belt_speed("cv101", 11.0)


def test_config_errors_name_the_key(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[sp201]\ndischarge_rate_kg_s = 3000.0\n")
    with pytest.raises(ValidationError, match="sp201.discharge_rate_kg_s"):
        load_config(bad)
    bad.write_text("[[feed.lots]]\nsource = 0\nduration_s = 1\nfeed_rate_kg_s = 1\n"
                   "grade = 2.0\nhardness = 1\n")
    with pytest.raises(ValidationError, match=r"feed.lots\[0\].grade"):
        load_config(bad)
    assert "report_outflow" in load_nodemap()


def test_the_feed_lots_name_their_sources():
    # the paper's two sources, named by the default schedule's lots
    assert source_names(load_config()) == {0: "left source", 1: "right source"}
    lots = copy.deepcopy(load_config()["feed"]["lots"])
    for lot in lots:
        del lot["name"]
    assert source_names(load_config(overrides={"feed": {"lots": lots}})) == {}
    lots[2]["name"] = "north pit"  # source 0 again, by another name
    lots[0]["name"] = "left source"
    with pytest.raises(ValidationError, match=r"feed.lots\[2\].name.*'left source'"):
        load_config(overrides={"feed": {"lots": lots}})
    lots[2]["name"] = " "
    with pytest.raises(ValidationError, match=r"feed.lots\[2\].name.*non-empty"):
        load_config(overrides={"feed": {"lots": lots}})


@pytest.mark.parametrize("model", ["fifo", "mixing"])
def test_stockpile_plus_plant_conserve_mass_and_ids(model):
    """Process and asset coupled directly: the audit finds nothing lost."""
    process = PlantProcess(load_config())
    asset = StockpileAsset(model, seed=3)
    asset.set_discharge_rate(process.discharge_rate_setpoint)
    sequence = 0
    for _ in range(300):
        for r in process.advance(1.0):
            asset.receive_bin(r.tracking_id, r.mass_kg, r.grade, r.hardness, r.source)
        out = asset.step(1.0)
        process.acknowledge(process.last_sequence)
        if out["tracking_ids"].size:
            sequence += 1
            process.report_outflow(sequence, out["tracking_ids"], out["masses"], out["grades"])
    summary = {"held": {str(k): v for k, v in asset.held_by_tracking_id().items()}}
    result = audit(process.ledger(), summary)
    assert result["bins_in"] > 100 and result["mass_out_kg"] > 0
    assert result["tracking_ids_lost"] == 0 and result["tracking_ids_duplicated"] == 0
    assert result["mass_balance_rel_error"] < 1e-9


def test_stockpile_sensors_and_display_fields():
    asset = StockpileAsset("fifo")
    asset.receive_bin(7, 500.0, 0.02, 1.2, source=1)
    asset.receive_bin(8, 500.0, 0.04, 1.4, source=0)
    asset.set_discharge_rate(100.0)
    asset.step(1.0)
    totals = asset.totals()
    assert math.isclose(totals["held_mass_kg"], 900.0)
    fields = asset.fields(8, 4)
    assert fields["mass"].shape == (4, 8)
    assert math.isclose(np.nansum(fields["mass"]), 900.0)
    # schematic velocities point towards the outlet at the origin
    table = asset.particle_table(100, 0)
    assert set(table["tracking_id"].tolist()) == {7, 8}
    feed = asset.predicted_feed(5.0)
    assert math.isclose(feed["mass_kg"], 500.0) and feed["tracking_ids"].tolist() == [7, 8]
    with pytest.raises(ValidationError, match="mass"):
        asset.receive_bin(9, float("nan"), 0.1, 1.0)
    with pytest.raises(ValidationError, match="grade"):
        asset.receive_bin(9, 10.0, 1.1, 1.0)
    assert math.isclose(asset.totals()["held_mass_kg"], 900.0)


def test_discharge_starts_at_the_configured_time_and_an_operator_write_wins():
    config = load_config(overrides={"sp201": {"discharge_rate_kg_s": 900.0,
                                              "discharge_start_s": 90.0}})
    process = PlantProcess(config)
    process.advance(89.9)
    assert process.discharge_rate_setpoint == 0.0  # the pile fills first
    process.advance(0.2)
    assert process.discharge_rate_setpoint == 900.0
    early = PlantProcess(config)
    early.advance(10.0)
    early.set_discharge_rate(300.0)
    early.advance(200.0)
    assert early.discharge_rate_setpoint == 300.0
    with pytest.raises(ValidationError, match="sp201.discharge_start_s"):
        load_config(overrides={"sp201": {"discharge_start_s": -1.0}})


def test_cv301_carries_and_delivers_each_report_once_even_with_shifts_between_reports(plant):
    tid = plant.pending[0].tracking_id
    assert plant.report_outflow(1, [tid], [100.0], [0.01]) == "applied"
    for _ in range(100):  # several belt shifts, no report in between
        plant.advance(0.5)
    assert plant.delivered_mass_kg == pytest.approx(100.0)  # was 200: carried twice
    assert plant.bins_out == 1


def test_the_ledger_store_brings_back_the_whole_plant(plant, tmp_path):
    from opcua_server.ledger_store import LedgerStore

    store = LedgerStore(tmp_path / "ledger.sqlite")
    first = plant.pending[0].tracking_id
    plant.report_outflow(1, [first], [100.0], [0.02])
    plant.acknowledge(3)
    plant.set_discharge_rate(150.0)
    plant.advance(7.3)
    store.save(plant)
    store.close()
    again = PlantProcess(load_config())
    reopened = LedgerStore(tmp_path / "ledger.sqlite")
    assert reopened.load(again) and reopened.ledger_id == store.ledger_id
    assert again.state() == plant.state()
    assert again.ledger() == plant.ledger()
    assert [r.sequence for r in again.pending] == [r.sequence for r in plant.pending]
    # both go on identically: same bins, same tracking ids, same refusals of replays
    assert [r.tracking_id for r in again.advance(30.0)] == \
        [r.tracking_id for r in plant.advance(30.0)]
    assert again.report_outflow(1, [first], [100.0], [0.02]) == "already applied"
    with pytest.raises(ExchangeRefused):
        again.report_outflow(1, [first], [90.0], [0.02])


def test_a_ledger_file_that_is_not_sqlite_is_a_clear_error(tmp_path):
    from opcua_server.ledger_store import LedgerStore

    path = tmp_path / "ledger.sqlite"
    path.write_text("not a database\n" * 100)
    with pytest.raises(ValidationError, match=f"ledger: .*{path}"):
        LedgerStore(path)


def test_an_initial_inventory_comes_in_at_the_start_through_the_same_exchange():
    """sp201.initial_inventory_kg: 30 t of earlier production as CV101 bins at t = 0, in
    lots cycling through the feed schedule, once; the stockpile that takes them and
    then runs keeps every kilogram and id (audit)."""
    config = load_config(overrides={"sp201": {"initial_inventory_kg": 30000.0,
                                              "initial_lot_kg": 5000.0}})
    process = PlantProcess(config)
    first = process.advance(1.0)
    bin_kg = config["feed"]["lots"][0]["feed_rate_kg_s"]  # 2 m bins at 2 m/s: one second
    assert len(first) == 120 and all(r.time_s == 0.0 for r in first)
    assert math.isclose(sum(r.mass_kg for r in first), 30000.0, rel_tol=1e-12)
    assert all(r.mass_kg == bin_kg for r in first)
    lots = config["feed"]["lots"]
    grades = [r.grade for r in first]
    assert grades[:20] == [lots[0]["grade"]] * 20 and grades[20:40] == [lots[1]["grade"]] * 20
    assert [r.hardness for r in first[40:60]] == [lots[2]["hardness"]] * 20
    assert len({r.tracking_id for r in first}) == 120
    assert not any(r.time_s == 0.0 for r in process.advance(30.0))   # once only
    asset = StockpileAsset("fifo", seed=1)
    asset.set_discharge_rate(process.discharge_rate_setpoint)
    for r in first + process.pending[len(first):]:
        asset.receive_bin(r.tracking_id, r.mass_kg, r.grade, r.hardness, r.source)
    out = asset.step(60.0)
    process.acknowledge(process.last_sequence)
    process.report_outflow(1, out["tracking_ids"], out["masses"], out["grades"])
    summary = {"held": {str(k): v for k, v in asset.held_by_tracking_id().items()}}
    result = audit(process.ledger(), summary)
    assert result["tracking_ids_lost"] == result["tracking_ids_duplicated"] == 0
    assert result["mass_held_kg"] > 20000.0 and result["mass_balance_rel_error"] < 1e-12
    # a plant restored from its ledger does not take the inventory in again
    restored = PlantProcess(config)
    restored.restore(process.state(), list(process.pending), [], [])
    before = restored.last_sequence
    after = restored.advance(1.0)
    assert all(r.time_s > 0 for r in after) and restored.last_sequence == before + len(after)


def test_a_bad_initial_inventory_is_refused_by_name():
    with pytest.raises(ValidationError, match="sp201.initial_inventory_kg"):
        load_config(overrides={"sp201": {"initial_inventory_kg": -1.0}})
    with pytest.raises(ValidationError, match="sp201.initial_lot_kg"):
        load_config(overrides={"sp201": {"initial_lot_kg": 0.0}})
