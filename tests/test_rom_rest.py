"""The resting bulk (``surrogate.rom.rest``, ``RomStorage(rest_fraction=...)``) and
the column-fill diagnosis that motivated it (``surrogate.rom.column_profile``)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cosim.errors import ValidationError
from surrogate.rom import column_profile, rest
from surrogate.rom.model import RomModel
from surrogate.rom.storage import (DEFAULT_MODEL, FIXED_GRID_MODEL, LOOSE_MODEL, REGISTERED_MODEL,
                                   RomStorage)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "surrogate" / "rom" / "data"


def test_cells_slower_than_the_share_of_the_outlet_speed_rest():
    model = RomModel.load(DEFAULT_MODEL)
    container = model.container
    speed = rest.outlet_speed(2000.0, container)
    assert speed == pytest.approx(2000.0 / (container.areal_density * container.outlet_width))
    field = np.zeros((2, 3, 2))
    field[0, 0] = (0.0, -0.07 * speed)   # slower than 0.08 of it: rests
    field[0, 1] = (0.05 * speed, -0.06 * speed)  # |v| = 0.078: rests
    field[1, 2] = (0.0, -0.09 * speed)   # moves on
    out = rest.at_rest(field, 2000.0, container, 0.08)
    assert np.array_equal(out[0, 0], [0.0, 0.0]) and np.array_equal(out[0, 1], [0.0, 0.0])
    assert np.array_equal(out[1, 2], field[1, 2])
    assert rest.at_rest(field, 0.0, container, 0.08) is field  # no discharge: as it is
    assert rest.at_rest(field, 2000.0, container, 0.0) is field  # off
    from dataclasses import replace

    point = replace(container, outlet_width=0.0)  # no outlet speed: off works, a share not
    assert rest.at_rest(field, 2000.0, point, 0.0) is field
    with pytest.raises(ValidationError, match="rest_fraction.*point outlet"):
        rest.at_rest(field, 2000.0, point, 0.08)


@pytest.mark.parametrize("model_file, share", [(FIXED_GRID_MODEL, 0.08), (REGISTERED_MODEL, 0.06),
                                               (LOOSE_MODEL, 0.06)],
                         ids=["fixed_grid", "registered", "loose"])
def test_the_share_is_fitted_on_the_training_design_by_youdens_index(model_file, share):
    model = RomModel.load(model_file)
    result = rest.fit(DATA / "paper_design", model)
    # what `rom train` fitted and the shipped file keeps
    assert result["best"] == model.rest_fraction == share
    assert model.validation["rest"] == result
    assert result["youden"] == pytest.approx(
        [r - m for r, m in zip(result["rest_stopped"], result["moving_stopped"])])
    # a larger share stops more of both
    assert np.all(np.diff(result["rest_stopped"]) >= 0)
    assert np.all(np.diff(result["moving_stopped"]) >= 0)
    assert result["cells"]["resting"] > result["cells"]["moving"] > 1000


def test_no_share_is_fitted_for_a_point_outlet_or_a_design_that_never_discharges():
    from dataclasses import replace

    from surrogate.rom import doe

    model = RomModel.load(DEFAULT_MODEL)
    samples = doe.load_samples(DATA / "paper_design")
    idle = dict(samples, discharge_rate=np.zeros_like(samples["discharge_rate"]))
    assert rest.fit_samples(idle, model)["best"] == 0.0
    model.container = replace(model.container, outlet_width=0.0)
    assert rest.fit_samples(samples, model)["best"] == 0.0


def test_the_model_file_keeps_its_share_and_a_file_without_one_is_off(tmp_path):
    model = RomModel.load(DEFAULT_MODEL)
    model.rest_fraction = 0.05
    assert RomModel.load(model.save(tmp_path / "share.npz")).rest_fraction == 0.05
    model.rest_fraction = 0.0
    path = model.save(tmp_path / "off.npz")
    with np.load(path) as stored:
        assert "rest_fraction" not in json.loads(str(stored["header"]))
    assert RomModel.load(path).rest_fraction == 0.0


def test_the_storage_rests_its_predicted_field_and_refuses_a_bad_share():
    storage = RomStorage()  # the model file's share
    share = RomModel.load(DEFAULT_MODEL).rest_fraction
    assert storage.rest_fraction == storage.model.rest_fraction == share > 0
    mass = np.zeros(storage.model.grid.shape)
    mass[:10, 30:50] = storage.model.full_cell_mass
    plain = storage.model.predict(mass, 2000.0, 2000.0, check=False)
    assert np.array_equal(storage.predicted_field(mass, 2000.0, 2000.0),
                          rest.at_rest(plain, 2000.0, storage.container, share))
    assert not np.array_equal(storage.predicted_field(mass, 2000.0, 2000.0), plain)
    assert np.array_equal(RomStorage(rest_fraction=0.0).predicted_field(mass, 2000.0, 2000.0),
                          plain)  # off
    assert np.array_equal(RomStorage(rest_fraction=0.2).predicted_field(mass, 2000.0, 2000.0),
                          rest.at_rest(plain, 2000.0, storage.container, 0.2))
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValidationError, match="rest_fraction"):
            RomStorage(rest_fraction=bad)
    from dataclasses import replace

    model = RomModel.load(DEFAULT_MODEL)
    model.container = replace(model.container, outlet_width=0.0)
    with pytest.raises(ValidationError, match="rest_fraction.*point outlet"):
        RomStorage(model)  # the file's share, at once, not at the first discharge
    with pytest.raises(ValidationError, match="rest_fraction.*point outlet"):
        RomStorage(model, rest_fraction=0.08)
    assert RomStorage(model, rest_fraction=0.0).rest_fraction == 0.0
    model.rest_fraction = 0.0  # as `rom train` fits it for a point outlet
    assert RomStorage(model).rest_fraction == 0.0


def test_the_fit_refuses_a_folder_without_a_design_with_exit_2(tmp_path):
    done = subprocess.run([sys.executable, "-m", "surrogate.rom.rest", "--data",
                           str(tmp_path / "none")], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2
    assert "--data" in done.stderr and "Traceback" not in done.stderr


def test_the_column_profile_compares_the_rom_with_every_replica(tmp_path):
    code = column_profile.main(["--data", str(DATA / "paper_heldout"), "--scene",
                                "heldout_q2000", "--out", str(tmp_path)])
    assert code == 0
    written = json.loads((tmp_path / "column_profile_heldout_q2000.json").read_text())
    assert (tmp_path / "column_profile_heldout_q2000.png").stat().st_size > 10_000
    rom, dem = np.array(written["rom"]), [np.array(d) for d in written["dem"]]
    assert len(dem) == 3 and all(d.shape == rom.shape for d in dem)
    assert rom.shape == (len(written["time_s"]), len(written["x_m"]))
    # the replicas' fill is their stored mass per column over rho_A dx
    model = RomModel.load(DEFAULT_MODEL)
    with np.load(DATA / "paper_heldout" / "train" / "heldout_q2000_r0.npz") as stored:
        first = stored["mass"][0].astype(np.float64).sum(axis=0)
    assert dem[0][0] == pytest.approx(first / (model.container.areal_density
                                               * model.grid.dx))
    flanks = np.array(written["flanks"])
    assert written["summary"]["dem"][0]["flank_change_m"] == pytest.approx(
        float((dem[0][-1] - dem[0][0])[flanks].mean()))
    passing = written["row_flux"]
    assert passing["regions"] == ["core", "funnel edge", "flanks"]
    assert np.array(passing["dem"]).shape == np.array(passing["predicted"]).shape == (
        len(column_profile.ROW_FLUX_HEIGHTS), 3)
    assert np.array(written["rom_flux"]).shape == (len(column_profile.ROW_FLUX_HEIGHTS), 3)
    assert len(written["rom_edge_flux"]) == len(passing["edge_dem"]) == model.grid.ny
    assert column_profile.main(["--data", str(DATA / "paper_heldout"), "--scene", "nope",
                                "--out", str(tmp_path)]) == 2


def test_the_flux_through_lines_and_into_the_funnel_is_mass_times_speed():
    """``column_profile.line_flux`` and ``edge_flux`` on full cells moving uniformly:
    a line carries (columns) dx w downward, the funnel's edge 2 dy c per row."""
    model = RomModel.load(DEFAULT_MODEL)
    grid, density = model.grid, model.container.areal_density
    full = np.full(grid.shape, density * grid.dx * grid.dy)
    x = grid.centres()[0]
    masks = list(column_profile.regions(x, model.container.outlet_x).values())
    down = np.zeros(grid.shape + (2,))
    down[..., 1] = -0.2
    lines = column_profile.flux_lines(grid, (4.0, 10.0))
    flux = column_profile.line_flux(full, down, grid, density, lines, masks)
    assert flux == pytest.approx(np.array([[m.sum() * grid.dx * 0.2 for m in masks]] * 2),
                                 rel=1e-12)
    towards = np.zeros(grid.shape + (2,))
    towards[..., 0] = np.where(x < model.container.outlet_x, 0.05, -0.05)[None, :]
    edge = column_profile.edge_flux(full, towards, grid, density, model.container.outlet_x)
    assert edge == pytest.approx(np.full(grid.ny, 2 * grid.dy * 0.05), rel=1e-12)
    with pytest.raises(ValidationError, match="heights"):
        column_profile.flux_lines(grid, (-1.0,))
