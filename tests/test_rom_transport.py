"""Mass-conserving bulk transport of the ROM (``surrogate.rom.transport``)."""

import numpy as np
import pytest

from cosim.errors import ValidationError
from surrogate.rom.container import Container
from surrogate.rom.grid import Grid
from surrogate.rom.storage import FIXED_GRID_MODEL, RomStorage
from surrogate.rom.transport import advect_faces, divergence, project, sample_faces

CONTAINER = Container(x_min=-10.0, x_max=10.0, floor=0.0, outlet_x=0.0, inlet_x=1.0,
                      areal_density=1600.0, repose_angle=0.6, outlet_width=2.0)
GRID = Grid.covering(-10.0, 10.0, 0.0, 8.0, 1.0)
FULL = CONTAINER.areal_density * GRID.dx * GRID.dy


def _heap_and_sink(rate: float):
    """A triangular heap's mass field (full cells inside) and a converging sink flow
    (not divergence free) towards the outlet."""
    x, y = GRID.centres()
    gx, gy = np.meshgrid(x, y)
    mass = np.where(gy < 6.0 - 0.6 * np.abs(gx), FULL, 0.0)
    r = np.maximum(np.hypot(gx, gy), 0.5)
    field = np.stack((-gx, -gy), axis=-1) * (rate / (CONTAINER.areal_density * r ** 2))[..., None]
    return mass, field


def test_the_projection_balances_every_bulk_cell_and_the_feeder_takes_the_outflow():
    rate = 300.0
    mass, field = _heap_and_sink(rate)
    u, v = project(field, mass, GRID, CONTAINER, rate)
    bulk = mass >= 0.9 * FULL
    div = divergence(u, v, GRID.dx, GRID.dy)
    assert np.abs(div[bulk]).max() < 1e-9 * np.abs(field).max()
    assert np.abs(u[:, 0]).max() == 0.0 and np.abs(u[:, -1]).max() == 0.0  # walls
    x, _ = GRID.centres()
    opening = np.abs(x - CONTAINER.outlet_x) < 0.5 * CONTAINER.outlet_width
    assert np.abs(v[0, ~opening]).max() == 0.0  # the floor beside the opening
    assert -v[0].sum() * GRID.dx == pytest.approx(rate / CONTAINER.areal_density, rel=1e-12)


def test_the_balanced_projection_feeds_the_bulk_through_its_surface_what_the_feeder_takes():
    rate = 300.0
    mass, field = _heap_and_sink(rate)
    u, v = project(field, mass, GRID, CONTAINER, rate, free_surface="flux")
    bulk = mass >= 0.9 * FULL
    div = divergence(u, v, GRID.dx, GRID.dy)
    assert np.abs(div[bulk]).max() < 1e-8 * np.abs(field).max()
    # net flux into the bulk through its surface faces = the feeder's outflow
    inward = 0.0
    for j, i in np.argwhere(bulk):
        if j == GRID.ny - 1 or not bulk[j + 1, i]:
            inward -= v[j + 1, i] * GRID.dx
        if i > 0 and not bulk[j, i - 1]:
            inward += u[j, i] * GRID.dy
        if i < GRID.nx - 1 and not bulk[j, i + 1]:
            inward -= u[j, i + 1] * GRID.dy
    assert inward == pytest.approx(rate / CONTAINER.areal_density, rel=1e-9)
    with pytest.raises(ValueError, match="free_surface"):
        project(field, mass, GRID, CONTAINER, rate, free_surface="rigid")


def test_the_face_interpolation_is_divergence_free_inside_a_balanced_cell():
    rate = 300.0
    mass, field = _heap_and_sink(rate)
    u, v = project(field, mass, GRID, CONTAINER, rate)
    bulk = np.argwhere(mass >= 0.9 * FULL)
    rng = np.random.default_rng(0)
    e = 1e-6
    for j, i in bulk[rng.choice(len(bulk), 20, replace=False)]:
        x = GRID.x_min + (i + rng.uniform(0.1, 0.9)) * GRID.dx
        y = GRID.y_min + (j + rng.uniform(0.1, 0.9)) * GRID.dy
        args = (u, v, GRID.x_min, GRID.y_min, GRID.dx, GRID.dy)
        dudx = (sample_faces(*args, x + e, y)[0] - sample_faces(*args, x - e, y)[0]) / (2 * e)
        dvdy = (sample_faces(*args, x, y + e)[1] - sample_faces(*args, x, y - e)[1]) / (2 * e)
        assert abs(dudx + dvdy) < 1e-6 * np.abs(field).max()


def test_advection_by_the_projected_field_keeps_the_bulk_density():
    """Particles packed evenly in the heap: advected for a while by the raw field they
    crowd towards the sink; by the projected one, every bulk cell away from the
    surface and the outlet keeps its count."""
    rate = 300.0
    mass, field = _heap_and_sink(rate)
    gx, gy = np.meshgrid(np.arange(-9.9, 10, 0.2), np.arange(0.1, 8, 0.2))
    cell_mass = GRID.cell_index(np.column_stack((gx.ravel(), gy.ravel())))
    inside = mass.ravel()[cell_mass] > 0
    start = np.column_stack((gx.ravel()[inside], gy.ravel()[inside]))
    u, v = project(field, mass, GRID, CONTAINER, rate)

    def counts(position):
        return np.bincount(GRID.cell_index(position), minlength=GRID.n_cells).reshape(GRID.shape)

    moved = start.copy()
    advect_faces(moved, u, v, GRID.x_min, GRID.y_min, GRID.dx, GRID.dy, 2.0, 40,
                 CONTAINER.x_min, CONTAINER.x_max, CONTAINER.floor)
    # deep cells, away from the outlet's cells: neither surface nor sink
    deep = np.zeros(GRID.shape, bool)
    deep[2:4, 3:17] = True
    deep[0:2, 8:12] = False
    before, after = counts(start)[deep], counts(moved)[deep]
    assert np.abs(after - before).max() <= 0.02 * before.max()
    from surrogate.rom.advect import advect

    raw = start.copy()
    advect(raw, np.ascontiguousarray(field), GRID.x_min, GRID.y_min, GRID.dx, GRID.dy, 2.0, 40,
           CONTAINER.x_min, CONTAINER.x_max, CONTAINER.floor)
    assert np.abs(counts(raw)[deep] - before).max() > 0.05 * before.max()


def test_bad_transport_options_are_refused_by_name():
    with pytest.raises(ValidationError, match="transport"):
        RomStorage(transport="magic")
    with pytest.raises(ValidationError, match="packing"):
        RomStorage(transport="projected", packing="shake")
    # a model file without storage settings runs the built-in defaults
    fixed_grid = RomStorage(FIXED_GRID_MODEL)
    assert fixed_grid.transport == "balanced" and fixed_grid.packing == "avalanche"
    with pytest.raises(ValidationError, match="relax"):
        RomStorage(transport="projected", relax=0.0)


@pytest.mark.filterwarnings("ignore::surrogate.rom.model.OutOfTrainingRange")
@pytest.mark.parametrize("options", [
    {"transport": "balanced", "packing": "avalanche"},
    {"transport": "projected", "packing": "column"},
    {"transport": "balanced", "packing": "none"},
    {"transport": "balanced", "packing": "loose", "void_gap": 0.2},
    {"velocity_model": "kinematic", "packing": "avalanche"},
    {"velocity_model": "kinematic", "packing": "none"},
    {"velocity_model": "hybrid", "packing": "avalanche"}])
def test_the_projected_rom_conserves_ids_and_mass_and_repeats_itself(options):
    from test_rom_surface import _run, _sink_model

    model = _sink_model()

    def run(seed):
        return _run(model, seed, steps=20, **options)

    store, storage, received, left = run(3)
    held = storage.held_ids()
    assert np.unique(left).size == left.size
    assert np.array_equal(np.sort(np.concatenate((left, held))), np.sort(received))
    assert store.total_mass(2) == pytest.approx(200.0 * 20, abs=256.0)
    assert store.total_mass(1) + store.total_mass(2) == pytest.approx(
        store.mass[store.slots(received)].sum(), rel=1e-12)
    velocity = storage.fields()["velocity"]
    assert velocity.shape == GRID.shape + (2,) and np.isfinite(velocity).all()
    ids, share = storage.predict(10.0, 200.0)
    assert share.sum() == pytest.approx(storage.feeder_credit_kg + 2000.0, rel=1e-9)
    again = run(3)
    assert np.array_equal(again[3], left)
    assert np.array_equal(again[0].position[again[0].slots(held)],
                          store.position[store.slots(held)])
