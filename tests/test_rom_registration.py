"""Height-following registration of the velocity fields (``surrogate.rom.registration``)
and the registered fit (``RomModel(registration="height")``).

By hand on small grids: a full column's levels are its cell centres (registration
is the identity), cells above a column's top and empty columns are 0, a field
linear in the registered coordinate comes back exactly. The registered fit of
flat piles whose flow has one shape in units of the pile's height predicts that
shape at a height it was not trained on, where the fixed grid's fit does not;
it saves and loads with its registration, and trains from the command line.
"""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_rom import CONTAINER, write_design  # noqa: E402

from cosim.errors import ValidationError  # noqa: E402
from surrogate.rom import registration  # noqa: E402
from surrogate.rom.grid import Grid  # noqa: E402
from surrogate.rom.model import RomModel  # noqa: E402

GRID = Grid.covering(0.0, 4.0, 0.0, 8.0, 1.0)  # 4 columns, 8 rows of 1 m
DENSITY = 100.0  # [kg/m^2]: a full cell holds 100 kg


def flat_pile(height: float) -> np.ndarray:
    """Mass field (ny, nx) [kg] of a pile ``height`` [m] high in every column."""
    filled = np.clip(height - np.arange(GRID.ny) * GRID.dy, 0.0, GRID.dy)
    return np.repeat(filled[:, None] * DENSITY * GRID.dx, GRID.nx, axis=1)


def shaped_flow(height: float, rate: float) -> np.ndarray:
    """A downward flow (ny, nx, 2) [m/s], rate [kg/s] / 1000 times eta (1 - eta)
    at eta = y / height in the pile, 0 above it."""
    centre = (np.arange(GRID.ny) + 0.5) * GRID.dy
    eta = centre / height
    speed = np.where(eta < 1.0, eta * (1.0 - eta), 0.0) * rate / 1000.0
    field = np.zeros((GRID.ny, GRID.nx, 2))
    field[..., 1] = -speed[:, None]
    return field


def test_column_heights_are_the_column_mass_over_the_density():
    mass = flat_pile(5.5)
    assert np.allclose(registration.column_heights(mass, GRID, DENSITY), 5.5)
    assert np.allclose(registration.column_heights(mass, GRID, 2 * DENSITY), 2.75)


def test_a_full_column_is_registered_as_it_is():
    rng = np.random.default_rng(0)
    velocity = rng.normal(size=(2, GRID.ny, GRID.nx, 2))
    mass = np.stack([flat_pile(8.0)] * 2)
    out = registration.register(velocity, mass, GRID, DENSITY)
    assert np.allclose(out, velocity, atol=1e-12)
    assert np.allclose(registration.unregister(out, mass, GRID, DENSITY), velocity, atol=1e-12)


def test_cells_above_the_top_and_empty_columns_are_zero():
    mass = flat_pile(4.0)[None].copy()
    mass[0, :, 2:] = 0.0  # an empty column (3) and one 0.4 m high (2),
    mass[0, 0, 2] = 0.4 * DENSITY  # less than half a cell
    registered = np.ones((1, GRID.ny, GRID.nx, 2))
    out = registration.unregister(registered, mass, GRID, DENSITY)
    assert np.all(out[0, :4, :2] == 1.0)  # under the 4 m top
    assert np.all(out[0, 4:] == 0.0)
    assert np.all(out[0, :, 2:] == 0.0)
    assert np.all(registration.register(registered, mass, GRID, DENSITY)[0, :, 2:] == 0.0)


def test_a_field_linear_in_the_registered_coordinate_comes_back_exactly():
    # a registered field linear in eta, mapped on a 6 m pile: linear in y there;
    # registered again it is the same at the levels whose heights lie between
    # the first and last cell centres under the top
    levels = (np.arange(GRID.ny) + 0.5) / GRID.ny
    registered = np.zeros((1, GRID.ny, GRID.nx, 2))
    registered[0, :, :, 0] = (2.0 + 3.0 * levels)[:, None]
    mass = flat_pile(6.0)[None]
    back = registration.unregister(registered, mass, GRID, DENSITY)
    centre = (np.arange(GRID.ny) + 0.5) * GRID.dy
    inside = centre < 6.0
    assert np.allclose(back[0, inside, :, 0], (2.0 + 3.0 * centre[inside] / 6.0)[:, None])
    again = registration.register(back, mass, GRID, DENSITY)
    heights = levels * 6.0
    within = (heights >= centre[0]) & (heights <= centre[inside][-1])
    assert within.sum() >= 5
    assert np.allclose(again[0, within, :, 0], registered[0, within, :, 0])


def _fitted(registered: bool) -> RomModel:
    heights, rates = (3.0, 5.0, 7.0), (1000.0, 2000.0)
    mass = np.array([flat_pile(h) for h in heights for _ in rates])
    velocity = np.array([shaped_flow(h, q) for h in heights for q in rates])
    q_out = np.array([q for _ in heights for q in rates])
    return RomModel(GRID, 1, 1, 1e-6, CONTAINER, registration="height" if registered else None,
                    registration_density=DENSITY if registered else None).fit(
        mass, q_out, np.zeros(q_out.size), velocity)


def test_the_registered_fit_carries_the_flow_to_a_height_it_was_not_trained_on():
    truth = shaped_flow(6.0, 1500.0)
    errors = {}
    for registered in (True, False):
        predicted = _fitted(registered).predict(flat_pile(6.0), 1500.0, check=False)
        errors[registered] = np.linalg.norm(predicted - truth) / np.linalg.norm(truth)
    assert errors[True] < 0.1
    assert errors[False] > 2 * errors[True]


def test_the_registration_follows_the_density_the_mass_is_packed_at():
    model = _fitted(True)
    # the same 6 m pile packed twice as densely: at its own density the flow stops
    # at its 6 m top; read at the fit's density it would be a 12 m pile
    dense = 2 * flat_pile(6.0)
    moving = np.abs(model.predict(dense, 1500.0, check=False,
                                  areal_density=2 * DENSITY)[..., 1]) > 0
    centre = (np.arange(GRID.ny) + 0.5) * GRID.dy
    assert np.array_equal(moving, np.repeat((centre < 6.0)[:, None], GRID.nx, axis=1))
    misread = np.abs(model.predict(dense, 1500.0, check=False)[..., 1]) > 0
    assert misread[6:].any()


def test_a_registered_model_saves_and_loads_with_its_registration(tmp_path):
    model = _fitted(True)
    path = model.save(tmp_path / "model.npz")
    loaded = RomModel.load(path)
    assert loaded.registration == "height" and loaded.registration_density == DENSITY
    assert np.array_equal(loaded.predict(flat_pile(6.0), 1500.0, check=False),
                          model.predict(flat_pile(6.0), 1500.0, check=False))
    plain = _fitted(False)
    assert "registration" not in plain.header()  # files without it load as before


@pytest.mark.parametrize("options, field", [
    ({"registration": "depth"}, "registration"),
    ({"registration": "height", "target": "flux"}, "registration"),
    ({"registration": "height", "registration_density": 0.0}, "registration_density"),
])
def test_bad_registration_options_are_refused_naming_the_field(options, field):
    with pytest.raises(ValidationError, match=field):
        RomModel(GRID, 1, 1, 1.0, CONTAINER, **options)


def test_the_cli_trains_a_registered_model(tmp_path):
    from minetwin.cli import main

    write_design(tmp_path)
    out = tmp_path / "model.npz"
    assert main(["rom", "train", "--data", str(tmp_path), "--out", str(out),
                 "--mass-modes", "4", "--velocity-modes", "4", "--ridge", "1",
                 "--registration", "height"]) == 0
    loaded = RomModel.load(out)
    assert loaded.registration == "height"
    assert 0.0 < loaded.registration_density
    assert "--registration height" in loaded.provenance["regenerate"]
