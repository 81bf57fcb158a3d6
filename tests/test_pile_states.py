"""``minetwin reproduce pile-states``: the paper's pile pictures from the shipped ROM.

The run is fed by the ROM's surface DEM (chaotic), so the test asserts exact
invariants (mass balance, ids) and one property of the two states that no
trajectory can turn: after 120 s at 2 t/s against 0.3 t/s of inflow (about
200 t drained through the outlet) the surface over the outlet is lower than
on the pointy pile the inlet built (measured on seeds 0-4: 35.7-36.1 m pointy,
20.0-20.9 m depleted).
"""

import json
import subprocess
import sys
import warnings

import numpy as np
import pytest

from cosim import plotstyle
from surrogate.rom import pile_states


@pytest.mark.slow
def test_the_quick_pile_states_run_conserves_mass_and_ids_and_depletes_over_the_outlet(
        tmp_path):
    done = subprocess.run([sys.executable, "-m", "minetwin.cli", "reproduce", "pile-states",
                           "--quick", "--quiet", "--out", str(tmp_path)], capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["checks_failed"] == []
    assert summary["mass_balance_rel_error"] < 1e-9
    assert summary["ids_held_equal_store"]
    pointy, depleted = summary["states"]["pointy"], summary["states"]["depleted"]
    assert pointy["held_kg"] == pytest.approx(pile_states.FILL_KG + pile_states.POINTY_INFLOW
                                              * pile_states.QUICK_POINTY_S, rel=1e-12)
    assert depleted["surface_over_outlet_m"] < pointy["surface_over_outlet_m"]
    for name in ("pile_states.png", "pile_residence_time.png"):
        assert (tmp_path / name).stat().st_size > 20_000


def test_the_pile_pictures_are_titled_labelled_and_colour_the_surface_layer_black(tmp_path):
    rng = np.random.default_rng(3)
    n = 200
    state = {"name": "pointy", "time": 20.0, "x": rng.uniform(-50, 50, n),
             "y": rng.uniform(0, 30, n), "diameter": np.full(n, 0.4),
             "mass": np.full(n, 100.0), "hardness": rng.choice([1.0, 2.0], n),
             "residence_time": rng.uniform(0, 800, n), "falling": np.arange(n) < 5}
    seen = {}

    def hook(fig, path):
        seen[path.name] = (plotstyle.problems(fig), fig._suptitle.get_text(), fig)

    plotstyle.SAVE_HOOKS.append(hook)
    try:
        pile_states.plot([state, {**state, "name": "depleted"}], tmp_path,
                         plotstyle.run_label(scenario="pile_states", seed=3, model="rom"))
    finally:
        plotstyle.SAVE_HOOKS.remove(hook)
    assert sorted(seen) == ["pile_residence_time.png", "pile_states.png"]
    for problems, title, fig in seen.values():
        assert problems == []
        assert "seed 3" in title and "rom" in title
        for ax in fig.axes[:2]:
            disks = ax.collections[0]
            colours = disks.to_rgba(disks.get_array())
            assert np.allclose(colours[:5, :3], 0.0)       # the surface layer: black
            assert not np.allclose(colours[5:, :3], 0.0)


def test_the_hanging_share_is_the_mass_over_emptied_cells():
    from surrogate.rom.container import Container
    from surrogate.rom.grid import Grid
    from surrogate.rom.hanging import EMPTY_FILL, hanging_share

    grid = Grid.covering(0.0, 4.0, 0.0, 6.0, 2.0)  # 3 rows of 2 columns, row 0 at the floor
    container = Container(x_min=0.0, x_max=4.0, floor=0.0, outlet_x=2.0, inlet_x=2.0,
                          areal_density=100.0)
    full = container.full_cell_mass(grid)
    field = np.zeros(grid.shape)
    field[:, 0] = full  # a full column rests on the floor
    assert hanging_share(field, grid, container) == 0.0
    field[2, 1] = full  # a cell over two empty ones hangs
    assert hanging_share(field, grid, container) == pytest.approx(1 / 4)
    field[1, 1] = EMPTY_FILL * full  # what it rests on holds just enough
    assert hanging_share(field, grid, container) == pytest.approx(
        EMPTY_FILL / (4 + EMPTY_FILL))  # now the thin cell is what hangs
    assert hanging_share(np.zeros(grid.shape), grid, container) == 0.0
    with pytest.raises(ValueError, match="shape"):
        hanging_share(field[:2], grid, container)


def test_the_loose_default_and_the_fixed_grid_rest_on_their_base_and_the_registered_option_hangs():
    """Statistics over seeds, not one trajectory: on the quick depleted state the
    default (the registered fit under the loose packing) and the fixed grid (avalanche
    packing) hang nothing over emptied cells on any seed, the registered option (no
    packing) always hangs more than the limit (measured on seeds 0-4: 0 and 0 against
    0.0103-0.0122; on the full run 0 and 0 against 0.0119-0.0191)."""
    from surrogate.rom.hanging import HANGING_LIMIT
    from surrogate.rom.storage import (DEFAULT_MODEL, FIXED_GRID_MODEL, LOOSE_MODEL,
                                       REGISTERED_MODEL)

    assert DEFAULT_MODEL == LOOSE_MODEL
    for model, hangs in ((LOOSE_MODEL, False), (FIXED_GRID_MODEL, False),
                         (REGISTERED_MODEL, True)):
        for seed in (0, 1, 2):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the drained pile leaves the residual range
                _, run = pile_states.run_states(quick=True, seed=seed, model=model)
            depleted = run["states"]["depleted"]["hanging_mass_share"]
            assert (depleted > HANGING_LIMIT) is hangs, (model.name, seed, depleted)
            assert run["states"]["pointy"]["hanging_mass_share"] <= HANGING_LIMIT
