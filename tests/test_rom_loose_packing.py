"""The loose packing (``surrogate.rom.surface.settle_loose``): voids close, nothing
else in a column moves, no particle rises, and avalanches bring the real tops to the
angle of repose."""

import numpy as np
import pytest

from cosim.errors import ValidationError
from surrogate.rom.container import Container
from surrogate.rom.grid import Grid
from surrogate.rom.hanging import hanging_share_of
from surrogate.rom.model import RomModel
from surrogate.rom.storage import REGISTERED_MODEL, RomStorage
from surrogate.rom.surface import settle_loose

CONTAINER = Container(x_min=-10.0, x_max=10.0, floor=0.0, outlet_x=0.0, inlet_x=1.0,
                      areal_density=1600.0, repose_angle=0.6, outlet_width=2.0)
GRID = Grid.covering(-10.0, 10.0, 0.0, 12.0, 1.0)
WIDTH = 0.5
MASS = 100.0
SLAB = MASS / (CONTAINER.areal_density * WIDTH)  # a particle's height in its column [m]


def _columns(position):
    return np.clip(((position[:, 0] - CONTAINER.x_min) / WIDTH).astype(int), 0,
                   round((CONTAINER.x_max - CONTAINER.x_min) / WIDTH) - 1)


def _tops(position):
    """Each column's real top [m]: its highest particle's upper edge (floor if empty)."""
    tops = np.full(round((CONTAINER.x_max - CONTAINER.x_min) / WIDTH), CONTAINER.floor)
    np.maximum.at(tops, _columns(position), position[:, 1] + 0.5 * SLAB)
    return tops


def _gaps(position):
    """Every void [m] between a particle's lower edge and the one below it (the floor
    for the lowest of a column)."""
    column = _columns(position)
    order = np.lexsort((position[:, 1], column))
    y, c = position[order, 1], column[order]
    below = np.where(np.r_[True, c[1:] != c[:-1]], CONTAINER.floor,
                     np.r_[0.0, y[:-1] + 0.5 * SLAB])
    return y - 0.5 * SLAB - below


def _bulk_over_a_void(rng):
    """A packed layer on the floor, a dilute block hanging 5 m over a void above it."""
    x = rng.uniform(-8.0, 8.0, 600)
    layer = np.column_stack((x[:300], rng.uniform(0.1, 1.0, 300)))
    block = np.column_stack((x[300:] / 3.0, rng.uniform(6.0, 9.0, 300)))
    return np.concatenate((layer, block))


def test_voids_close_and_no_particle_rises_or_moves_sideways():
    position = _bulk_over_a_void(np.random.default_rng(0))
    before = position.copy()
    mass = np.full(len(position), MASS)
    assert hanging_share_of(position, mass, GRID, CONTAINER) > 0.1  # the block hangs
    order = settle_loose(CONTAINER, WIDTH, position, mass, void_gap=0.2, sweeps=0)
    assert np.array_equal(np.sort(order), np.arange(len(position)))
    assert np.array_equal(position[:, 0], before[:, 0])
    assert (position[:, 1] <= before[:, 1]).all()
    assert _gaps(position).max() <= 0.2 + 1e-12
    assert hanging_share_of(position, mass, GRID, CONTAINER) == 0.0


def test_a_bulk_whose_voids_are_within_the_gap_is_left_as_it_is():
    """The field's spacing stays: a column dilute by less than the gap does not move."""
    rng = np.random.default_rng(1)
    column_x = CONTAINER.x_min + WIDTH * (rng.integers(14, 26, 200) + 0.5)
    position = np.column_stack((column_x, np.zeros(200)))
    for c in np.unique(column_x):
        here = np.flatnonzero(column_x == c)
        position[here, 1] = np.cumsum(SLAB + rng.uniform(0.0, 0.15, here.size)) - 0.5 * SLAB
    before = position.copy()
    settle_loose(CONTAINER, WIDTH, position, np.full(200, MASS), void_gap=0.15, sweeps=0)
    assert np.array_equal(position, before)


def test_avalanches_bring_the_real_tops_to_the_angle_of_repose_and_repeat():
    """A spike of 120 particles in one column slides until no column stands more than
    tan(repose) w over a neighbour; particles only move by whole columns."""
    position = np.column_stack((np.full(120, 0.25), SLAB * (np.arange(120) + 0.5)))
    mass = np.full(120, MASS)
    again = position.copy()
    settle_loose(CONTAINER, WIDTH, position, mass, void_gap=0.2, sweeps=500)
    tops = _tops(position)
    assert np.abs(np.diff(tops)).max() <= np.tan(CONTAINER.repose_angle) * WIDTH + 1e-12
    assert np.allclose((position[:, 0] - 0.25) / WIDTH, np.round((position[:, 0] - 0.25)
                                                                  / WIDTH))
    assert _gaps(position).max() <= 0.2 + 1e-12
    settle_loose(CONTAINER, WIDTH, again, mass, void_gap=0.2, sweeps=500)
    assert np.array_equal(again, position)


def test_the_storage_takes_the_models_gap_and_refuses_a_bad_one_by_name():
    model = RomModel.load(REGISTERED_MODEL)
    model.storage_settings = {**model.storage_settings, "packing": "loose", "void_gap": 0.7}
    storage = RomStorage(model, surface="rule")
    assert (storage.packing, storage.void_gap) == ("loose", 0.7)
    told = RomStorage(model, surface="rule", void_gap=0.5)
    assert (told.packing, told.void_gap) == ("loose", 0.5)
    for bad in (-0.1, float("nan")):
        with pytest.raises(ValidationError, match="void_gap"):
            RomStorage(REGISTERED_MODEL, surface="rule", packing="loose", void_gap=bad)
