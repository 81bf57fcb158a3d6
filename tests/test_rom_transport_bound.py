"""The ROM's transport driven by the DEM's own velocity field (``surrogate.rom.transport_bound``)."""

import json
from pathlib import Path

import numpy as np
import pytest

from cosim.errors import ValidationError
from surrogate.rom import evaluate, heldout_layout, metrics, transport_bound
from surrogate.rom.grid import Grid
from surrogate.rom.model import RomModel
from surrogate.rom.storage import FIXED_GRID_MODEL

ROOT = Path(__file__).resolve().parents[1]
HELDOUT = ROOT / "surrogate" / "rom" / "data" / "paper_heldout"


def test_window_mean_by_hand():
    times = np.array([0.0, 1.0, 2.0, 3.0])
    fields = np.arange(4.0)[:, None, None, None] * np.ones((4, 2, 3, 2))
    assert transport_bound.window_mean(times, fields, 1.2, 0.0)[0, 0, 0] == 1.0  # nearest
    assert transport_bound.window_mean(times, fields, 1.2, 1.0)[0, 0, 0] == 1.5  # 1 and 2
    assert transport_bound.window_mean(times, fields, 1.5, 5.0)[1, 2, 1] == 1.5  # all
    assert transport_bound.window_mean(times, fields, 10.0, 0.5)[0, 0, 0] == 3.0  # nearest


def test_the_field_is_extended_above_the_dem_pile_by_hand():
    # one sample, 4 rows, 3 columns; full cell 10 kg, so a cell of 5 kg or more is in the pile
    mass = np.array([[[10.0, 10.0, 0.0], [6.0, 2.0, 0.0], [1.0, 9.0, 0.0], [0.0, 0.0, 0.0]]])
    velocity = np.arange(24.0).reshape(1, 4, 3, 2)
    out = transport_bound.extended(velocity, mass, 10.0)
    assert np.array_equal(out[0, :2, 0], velocity[0, :2, 0])  # column 0: top at row 1
    assert np.array_equal(out[0, 2:, 0], velocity[0, [1, 1], 0])
    assert np.array_equal(out[0, :3, 1], velocity[0, :3, 1])  # column 1: top at row 2
    assert np.array_equal(out[0, 3, 1], velocity[0, 2, 1])
    assert np.array_equal(out[0, :, 2], velocity[0, :, 2])  # column 2: no pile, as it was


def test_window_distances_average_to_the_tracking_error():
    a = {"time": np.array([5.0, 10.0, 40.0, 50.0]), "tracking_id": np.array([1, 2, 2, 3]),
         "mass": np.array([1.0, 1.0, 1.0, 1.0])}
    b = {"time": np.array([5.0, 40.0]), "tracking_id": np.array([1, 3]),
         "mass": np.array([2.0, 1.0])}
    tv = metrics.window_distances(a, b, 0.0, 60.0)
    assert tv.tolist() == [0.5, 0.5]
    assert metrics.tracking_error(a, b, 0.0, 60.0) == pytest.approx(0.5)


def test_a_field_off_the_model_grid_or_a_negative_window_is_refused():
    model = RomModel.load(FIXED_GRID_MODEL)
    grid = model.grid
    good = np.zeros((2, grid.ny, grid.nx, 2))
    mass = np.zeros(good.shape[:-1])
    with pytest.raises(ValidationError, match="field_velocity"):
        transport_bound.ReplayedField(model, field_time=[0.0, 1.0], field_mass=mass,
                                      field_velocity=good[:, :, :-1], half_window=0.0)
    with pytest.raises(ValidationError, match="field_mass"):
        transport_bound.ReplayedField(model, field_time=[0.0, 1.0], field_mass=mass[:1],
                                      field_velocity=good, half_window=0.0)
    with pytest.raises(ValidationError, match="half_window"):
        transport_bound.ReplayedField(model, field_time=[0.0, 1.0], field_velocity=good,
                                      field_mass=mass, half_window=-1.0)


def test_the_replayed_field_replaces_the_prediction():
    """At time t the field the transport projects is the replica's extended field's
    window mean, not the fit."""
    with heldout_layout.scenes_laid_out(HELDOUT, ["heldout_q2000"]) as (folder, _):
        replica = evaluate.stable_replicas(folder / "heldout_q2000")[0]
    model = RomModel.load(FIXED_GRID_MODEL)
    storage = transport_bound.ReplayedField(model, field_time=replica["field_time"],
                                            field_velocity=replica["field_velocity"],
                                            field_mass=replica["field_mass"], half_window=15.0)
    t = float(replica["field_time"][40])
    mass = replica["field_mass"][40]
    field = transport_bound.extended(np.float64(replica["field_velocity"]),
                                     np.float64(replica["field_mass"]),
                                     model.container.full_cell_mass(model.grid))
    expected = transport_bound.window_mean(np.float64(replica["field_time"]), field, t, 15.0)
    assert np.abs(expected).max() > 0.1  # the scene's funnel flow
    assert np.array_equal(storage._predicted(t, 2000.0, mass), expected)


def test_a_projection_keeps_what_the_modes_span_and_drops_the_rest():
    rng = np.random.default_rng(0)
    modes = np.linalg.qr(rng.normal(size=(2 * 3 * 4, 3)))[0].T  # 3 orthonormal rows
    inside = (rng.normal(size=(2, 3)) @ modes).reshape(2, 3, 4, 2)
    across = rng.normal(size=(2, 3 * 4 * 2))
    across -= (across @ modes.T) @ modes  # orthogonal to every mode
    out = transport_bound.projected(inside + across.reshape(2, 3, 4, 2), modes)
    assert np.allclose(out, inside, atol=1e-12)


def test_the_first_modes_are_the_shipped_models_velocity_basis():
    """``modes:4`` replays in the basis the shipped 4-mode fit predicts in."""
    model = RomModel.load(FIXED_GRID_MODEL)
    basis = transport_bound.velocity_basis()
    own = model.arrays["velocity_modes"]  # (2 cells, 4), orthonormal columns
    assert own.shape[1] == 4
    # the same subspace (signs of SVD vectors are arbitrary): the projections agree
    assert np.allclose(basis[:4].T @ basis[:4], own @ own.T, atol=1e-9)


def test_the_fit_at_the_dem_state_is_the_models_prediction_there():
    with heldout_layout.scenes_laid_out(HELDOUT, ["heldout_q2000"]) as (folder, _):
        replica = evaluate.stable_replicas(folder / "heldout_q2000")[0]
    model = RomModel.load(FIXED_GRID_MODEL)
    storage = transport_bound.FittedAtDemState(model, field_time=replica["field_time"],
                                               field_mass=replica["field_mass"],
                                               half_window=0.0)
    t = float(replica["field_time"][40])
    own_mass = np.zeros((model.grid.ny, model.grid.nx))  # not what the field is taken at
    expected = storage.predicted_field(np.float64(replica["field_mass"][40]), 2000.0, 0.0)
    assert np.abs(expected).max() > 0.1
    assert np.array_equal(storage._predicted(t, 2000.0, own_mass), expected)
    with pytest.raises(ValidationError, match="field_mass"):
        transport_bound.FittedAtDemState(model, field_time=[0.0],
                                         field_mass=np.zeros((1, 2, 2)), half_window=0.0)


def test_modes_need_a_model_on_the_training_designs_grid(tmp_path, capsys):
    shipped = RomModel.load(FIXED_GRID_MODEL)
    grid = Grid.covering(-10.0, 10.0, 0.0, 8.0, 1.0)
    rng = np.random.default_rng(0)
    small = RomModel(grid, 2, 2, 1.0, shipped.container).fit(
        rng.uniform(0.0, 1.0, (6, grid.ny, grid.nx)), np.full(6, 100.0), np.zeros(6),
        rng.normal(size=(6, grid.ny, grid.nx, 2)))
    path = small.save(tmp_path / "small.npz")
    assert transport_bound.main(["--data", str(HELDOUT), "--out", str(tmp_path / "out"),
                                 "--model", str(path), "--field", "modes:4"]) == 2
    assert "--field" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_bound_on_a_held_out_scene(tmp_path):
    code = transport_bound.main(["--data", str(HELDOUT), "--scene", "heldout_q2000",
                                 "--half-window", "180", "--packing", "none",
                                 "--landing-spread", "0", "--landing-spread", "3",
                                 "--field", "dem", "--field", "modes:4",
                                 "--rom-seeds", "1", "--out", str(tmp_path)])
    assert code == 0
    assert (tmp_path / "transport_bound.png").stat().st_size > 0
    result = json.loads((tmp_path / "transport_bound.json").read_text())["heldout_q2000"]
    replicas = result["replicas"]
    assert replicas == 3 and result["rom_seeds"] == 1
    # the DEM's mean settled density on the shipped model's training design (packing.py)
    assert result["packing_density_kg_m2"] == pytest.approx(564.2, abs=0.05)
    entries = [result["dem_noise_floor"], result["rom"], *result["bounds"]]
    # every pair once; the ROM against each replica; each replica's field against the others
    counts = [replicas * (replicas - 1) // 2, replicas] + [replicas * (replicas - 1)] * 4
    assert [e["tracking_error"]["n"] for e in entries] == counts
    assert {b["half_window_s"] for b in result["bounds"]} == {180.0}
    assert {b["packing"] for b in result["bounds"]} == {"none"}
    assert [(b["field"], b["landing_spread_m"]) for b in result["bounds"]] == [
        ("dem", 0.0), ("dem", 3.0), ("modes:4", 0.0), ("modes:4", 3.0)]
    assert result["bounds"][1]["tracking_error"] != result["bounds"][0]["tracking_error"]
    # the field projected on 4 modes moves the pile another way than the whole field
    assert result["bounds"][2]["tracking_error"] != result["bounds"][0]["tracking_error"]
    for entry in entries:
        full, merged = entry["tracking_error"], entry["lumped"]
        assert 0.0 <= full["min"] <= full["mean"] <= full["max"] <= 1.0
        assert merged["mean"] <= full["mean"] + 1e-12  # merging ids never raises a distance
        assert len(entry["window_distance"]) == 6  # 180 s in 30 s windows
        assert np.mean(entry["window_distance"]) == pytest.approx(full["mean"], rel=1e-9)
    # the floor is the one `minetwin rom evaluate` reports
    with heldout_layout.scenes_laid_out(HELDOUT, ["heldout_q2000"]) as (folder, _):
        scene = folder / "heldout_q2000"
        runs = evaluate.stable_replicas(scene)
        t0 = float(runs[0]["t0"])
        floor = evaluate.noise_floor([evaluate.outflow_of(r) for r in runs], t0,
                                     t0 + evaluate.scenario_duration(scene))
    assert result["dem_noise_floor"]["tracking_error"]["mean"] == pytest.approx(
        floor["tracking_error"], rel=1e-12)


@pytest.mark.parametrize("argument, field", [
    (["--scene", "nope"], "--scene"),
    (["--half-window", "-1"], "--half-window"),
    (["--packing", "tight"], "--packing"),
    (["--rom-seeds", "0"], "rom_seeds"),
    (["--packing-density", "0"], "--packing-density"),
    (["--landing-spread", "-1"], "--landing-spread"),
    (["--field", "fitted"], "--field"),
    (["--field", "modes:0"], "--field"),
    (["--field", "modes:x"], "--field"),
    (["--field", "modes:100000"], "--field"),
])
def test_bad_input_exits_2_naming_the_field(argument, field, tmp_path, capsys):
    assert transport_bound.main(["--data", str(HELDOUT), "--out", str(tmp_path),
                                 *argument]) == 2
    assert field in capsys.readouterr().err
    assert not (tmp_path / "transport_bound.json").exists()
