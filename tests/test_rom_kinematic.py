"""The kinematic funnel-flow field (``surrogate.rom.kinematic``) and the ROM option using it."""

import json

import numpy as np
import pytest

from cosim.errors import ValidationError
from surrogate.rom import kinematic, rest
from surrogate.rom.container import Container
from surrogate.rom.grid import Grid
from surrogate.rom.storage import RomStorage

CONTAINER = Container(x_min=-60.0, x_max=60.0, floor=0.0, outlet_x=2.0, inlet_x=0.0,
                      areal_density=600.0, outlet_width=8.0)
FINE = Grid(x_min=-58.0, x_max=62.0, y_min=0.0, y_max=40.0, nx=960, ny=80)
"""0.125 m x 0.5 m cells, symmetric about the outlet at x = 2 m."""


def test_every_row_carries_the_outlets_flux_and_the_field_is_symmetric_about_the_outlet():
    rate = 2000.0
    field = kinematic.velocity_field(FINE, CONTAINER, rate, diffusion_length=1.0)
    flux = rate / CONTAINER.areal_density
    carried = -field[..., 1].sum(axis=1) * FINE.dx
    assert carried == pytest.approx(np.full(FINE.ny, flux), rel=1e-9)
    assert np.array_equal(field[:, ::-1, 1], field[..., 1])  # w even about x_o
    assert np.array_equal(field[:, ::-1, 0], -field[..., 0])  # u odd: towards the axis
    x, _ = FINE.centres()
    assert (field[:, x > CONTAINER.outlet_x, 0] <= 0.0).all()
    # beside the axis (half a cell off it) at height h: Q' / sqrt(4 pi B h) exp(-x^2 / 4 B h)
    _, y = FINE.centres()
    expected = flux / np.sqrt(4.0 * np.pi * y) * np.exp(-(0.5 * FINE.dx) ** 2 / (4.0 * y))
    assert -field[:, 480, 1] == pytest.approx(expected, rel=1e-12)


def test_the_field_is_divergence_free_and_still_without_discharge():
    field = kinematic.velocity_field(FINE, CONTAINER, 1500.0)
    du_dx = np.gradient(field[..., 0], FINE.dx, axis=1)
    dv_dy = np.gradient(field[..., 1], FINE.dy, axis=0)
    inner = (slice(10, -1), slice(1, -1))  # central differences, away from the source
    scale = np.abs(dv_dy[inner]).max()
    assert np.abs(du_dx + dv_dy)[inner].max() < 0.02 * scale
    assert not kinematic.velocity_field(FINE, CONTAINER, 0.0).any()


def _design(directory, diffusion_length):
    """A design folder of three runs (at rest, 800 and 2000 kg/s) whose velocity is
    the kinematic field of ``diffusion_length`` [m] over a full bed."""
    grid = Grid(x_min=-40.0, x_max=40.0, y_min=0.0, y_max=30.0, nx=40, ny=15)
    container = Container(x_min=-40.0, x_max=40.0, floor=0.0, outlet_x=0.0, inlet_x=0.0,
                          areal_density=600.0, outlet_width=8.0)
    (directory / "train").mkdir(parents=True)
    (directory / "doe.json").write_text(json.dumps({"grid": grid.to_dict(),
                                                    "container": container.to_dict()}))
    for rate in (0.0, 800.0, 2000.0):
        velocity = kinematic.velocity_field(grid, container, rate, diffusion_length)
        np.savez(directory / "train" / f"out{rate:.0f}.npz", time=np.arange(10.0),
                 mass=np.full((10,) + grid.shape, 600.0 * grid.dx * grid.dy),
                 velocity=np.repeat(velocity[None], 10, axis=0),
                 discharge_rate=np.full(10, rate), inflow_rate=np.zeros(10))


def test_the_fit_recovers_the_diffusion_length_of_its_data(tmp_path):
    _design(tmp_path, 0.8)
    fit = kinematic.fit_diffusion_length(tmp_path)
    assert fit["diffusion_length"] == pytest.approx(0.8, rel=2e-3)
    assert fit["rms_error"] < 1e-3 * fit["rms_dem"]
    assert fit["samples"] == 20  # the run at rest left out
    runs = kinematic.compare_on_design(tmp_path, diffusion_length=0.8)
    assert sorted(runs) == ["out2000", "out800"]
    assert runs["out800"]["rel_error"]["kinematic"] < 1e-6
    assert runs["out800"]["axis"]["kinematic"] == pytest.approx(runs["out800"]["axis"]["dem"],
                                                                rel=1e-6)


def test_the_storage_moves_its_bulk_by_the_kinematic_field_on_request():
    with pytest.raises(ValidationError, match="velocity_model"):
        RomStorage(velocity_model="magic")
    with pytest.raises(ValidationError, match="diffusion_length"):
        RomStorage(velocity_model="kinematic", diffusion_length=0.0)
    assert RomStorage().velocity_model == "regressed"
    storage = RomStorage(velocity_model="kinematic", diffusion_length=0.9)
    mass = np.zeros(storage.model.grid.shape)
    field = kinematic.velocity_field(storage.model.grid, storage.container, 1200.0, 0.9)
    # the model file's resting bulk applies to every velocity model; off, the field as it is
    assert storage.rest_fraction == storage.model.rest_fraction > 0.0
    assert np.array_equal(storage.predicted_field(mass, 1200.0, 0.0),
                          rest.at_rest(field, 1200.0, storage.container, storage.rest_fraction))
    off = RomStorage(velocity_model="kinematic", diffusion_length=0.9, rest_fraction=0.0)
    assert np.array_equal(off.predicted_field(mass, 1200.0, 0.0), field)


def test_the_hybrid_takes_the_faster_downward_speed_above_the_feeder_zone_only():
    grid = Grid(x_min=-10.0, x_max=10.0, y_min=0.0, y_max=8.0, nx=10, ny=8)  # 1 m rows
    container = Container(x_min=-10.0, x_max=10.0, floor=0.0, outlet_x=0.0, inlet_x=0.0,
                          areal_density=600.0, outlet_width=4.0, feeder_zone_height=1.5)
    rng = np.random.default_rng(0)
    regressed = rng.normal(0.0, 0.2, grid.shape + (2,))
    kinematic_part = kinematic.velocity_field(grid, container, 1500.0, 1.0)
    hybrid = kinematic.hybrid_field(regressed, kinematic_part, grid, container)
    assert np.array_equal(hybrid[..., 0], regressed[..., 0])  # the regression's sideways flow
    assert np.array_equal(hybrid[:2], regressed[:2])  # rows at 0.5 and 1.5 m: the feeder's
    down, down_r, down_k = -hybrid[2:, :, 1], -regressed[2:, :, 1], -kinematic_part[2:, :, 1]
    assert np.array_equal(down, np.maximum(down_r, down_k))
    assert (down > down_r).any() and (down == down_r).any()
    # a regression faster everywhere is left as it is; the inputs are not changed
    fast = regressed.copy()
    fast[..., 1] = -5.0
    assert np.array_equal(kinematic.hybrid_field(fast, kinematic_part, grid, container), fast)
    assert np.array_equal(fast[..., 1], np.full(grid.shape, -5.0))


def test_the_storage_moves_its_bulk_by_the_hybrid_field_on_request():
    with pytest.raises(ValidationError, match="diffusion_length"):
        RomStorage(velocity_model="hybrid", diffusion_length=-1.0)
    storage = RomStorage(velocity_model="hybrid", diffusion_length=0.9)
    grid, container = storage.model.grid, storage.container
    mass = np.full(grid.shape, 0.9 * container.areal_density * grid.dx * grid.dy)
    expected = kinematic.hybrid_field(
        storage.model.predict(mass, 1200.0, 600.0, check=False),
        kinematic.velocity_field(grid, container, 1200.0, 0.9), grid, container)
    assert np.array_equal(storage.predicted_field(mass, 1200.0, 600.0),
                          rest.at_rest(expected, 1200.0, container, storage.rest_fraction))
