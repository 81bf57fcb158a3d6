"""The ROM's packing density option (``RomStorage(packing_density=...)``) and the
DEM's settled-density measurement (``surrogate.rom.packing``)."""

import json

import numpy as np
import pytest

from cosim.errors import ValidationError
from surrogate.rom import packing
from surrogate.rom.surface import PARTICLES_PER_COLUMN
from test_rom_surface import CONTAINER, GRID, _run, _sink_model


def _stacked_density(store, held) -> list:
    """Areal density [kg/m^2] the held particles are stacked at, measured from their
    positions and masses: in a packing column of width w (the rule of
    ``surface.column_width``: ``PARTICLES_PER_COLUMN`` particle extents of the
    median particle, rounded to whole columns over the container), two neighbours
    m1, m2 of a stack packed at rho lie (m1 + m2) / (2 rho w) apart. Columns more
    than 2 m from the outlet (the feeder takes particles from below there). Tried
    at 1600 and 1200 kg/m^2: only the density it was packed at gives one value."""
    slots = store.slots(held)
    position, mass = store.position[slots, :2], store.mass[slots]
    found = []
    for rho in (1600.0, 1200.0):
        width = PARTICLES_PER_COLUMN * (float(np.median(mass)) / rho) ** 0.5
        columns = round((CONTAINER.x_max - CONTAINER.x_min) / width)
        width = (CONTAINER.x_max - CONTAINER.x_min) / columns
        column = ((position[:, 0] - CONTAINER.x_min) / width).astype(int)
        centre = CONTAINER.x_min + (column + 0.5) * width
        values = []
        for c in np.unique(column[np.abs(centre) > 2.0]):
            order = np.argsort(position[column == c, 1])
            y, m = position[column == c, 1][order], mass[column == c][order]
            values.append((m[1:] + m[:-1]) / (2.0 * width * np.maximum(np.diff(y), 1e-12)))
        values = np.concatenate(values)
        if np.ptp(values) < 1e-6 * values.mean():  # one density: a packed stack
            found.append(float(values.mean()))
    return found


@pytest.mark.filterwarnings("ignore::surrogate.rom.model.OutOfTrainingRange")
def test_the_bulk_packs_at_the_given_density_and_the_run_repeats_itself():
    model = _sink_model()
    assert CONTAINER.areal_density == 1600.0
    runs = {}
    for density in (None, 1200.0):
        store, storage, received, left = _run(model, 4, steps=3, surface="rule",
                                              packing_density=density)
        held = storage.held_ids()
        runs[density] = (_stacked_density(store, held),
                         store.position[store.slots(held), 1].max(), left)
        # the ids and the mass are kept either way
        assert np.array_equal(np.sort(np.concatenate((left, held))), np.sort(received))
        assert storage.bulk_areal_density() == (1600.0 if density is None else density)
    # the placed heap is at 1600 kg/m^2 (256 kg per 0.4 m x 0.4 m); packed again at
    # 1200 it stands higher
    assert runs[None][0] == [pytest.approx(1600.0, rel=1e-9)]
    assert runs[1200.0][0] == [pytest.approx(1200.0, rel=1e-9)]
    assert runs[1200.0][1] > 1.1 * runs[None][1]
    assert model.container.areal_density == 1600.0  # the model keeps its own container
    again = _run(model, 4, steps=3, surface="rule", packing_density=1200.0)
    assert np.array_equal(again[3], runs[1200.0][2])


def test_the_option_round_trips_through_a_checkpoint_and_refuses_bad_values(tmp_path):
    from surrogate.checkpoint import load_checkpoint, save_checkpoint

    storage = _run(_sink_model(), 1, steps=1, surface="rule", packing_density=1200.0)[1]
    save_checkpoint(tmp_path / "rom.ckpt", storage)
    back = load_checkpoint(tmp_path / "rom.ckpt")
    assert back.packing_density == 1200.0 and back.container.areal_density == 1200.0
    assert back.bulk_areal_density() == storage.bulk_areal_density() == 1200.0
    with pytest.raises(ValidationError, match="packing_density"):
        _run(_sink_model(), 1, steps=0, packing_density=0.0)


def test_the_settled_density_is_the_mean_of_the_covered_cells(tmp_path):
    """Two synthetic runs: a column of full cells under a half-full top, and the
    feeder's bottom cells nearly empty (left out)."""
    full = CONTAINER.areal_density * GRID.dx * GRID.dy
    (tmp_path / "train").mkdir()
    for name, fill in (("a", 0.9), ("b", 0.8)):
        mass = np.zeros((2,) + GRID.shape, np.float32)
        mass[:, :4, 5] = fill * full     # covered: rows 0-2 (row 3 under the half-full top)
        mass[:, 4, 5] = 0.5 * full       # the top: not covered
        mass[:, 0, 9:11] = 0.1 * full    # the feeder's row (opening 2 m at x = 0)
        mass[:, 1, 9:11] = full
        np.savez(tmp_path / "train" / f"{name}.npz", mass=mass)
    (tmp_path / "doe.json").write_text(json.dumps({"grid": GRID.to_dict(),
                                                   "container": CONTAINER.to_dict()}))
    result = packing.settled_density(tmp_path)
    assert result["per_run"]["a"] == [pytest.approx(0.9 * 1600.0), 8]
    assert result["per_run"]["b"] == [pytest.approx(0.8 * 1600.0), 8]
    assert result["density"] == pytest.approx(0.85 * 1600.0)
    assert result["fraction"] == pytest.approx(0.85)
