"""Held-out DEM runs of the speed-vs-accuracy chart: a forced time step that
blows the DEM up is stopped and recorded as unstable (when, why) instead of
crawling on; a stable step runs to the end with its fields.

A tiny stockpile (an 8 m floor, a 3 t pile of ~30 disks, 8 s scenario)
keeps this to a few seconds.
"""

import numpy as np
import pytest

from surrogate.rom import doe
from surrogate.rom import evaluate as ev

DURATION = 8
"""Simulated seconds of the tiny held-out scenario [s]."""


def tiny_config():
    return doe.training_config(floor_width=8.0, inlets=[[0.0, 4.0]], outlet_width=1.5)


@pytest.fixture(scope="module")
def heldout(tmp_path_factory):
    """A held-out scenario directory: settled tiny pile and its emissions."""
    directory = tmp_path_factory.mktemp("heldout")
    dem, _ = doe.build_pile(tiny_config(), 3000.0, seed=3)
    dem.save_checkpoint(directory / "initial.npz")
    scenario = doe.Scenario("tiny", fill=3000.0, discharge_rate=150.0, inflow_rate=150.0,
                            duration=DURATION)
    ev._write_emissions(directory, dem, scenario, seed=5)
    return directory


def test_forced_huge_step_is_stopped_and_recorded_unstable(heldout):
    grid = doe.grid_of(tiny_config())
    ev._run_heldout_dem(heldout, "dem_dt20", grid, 0.0, 20.0, 0, None)
    run = ev.load_run(heldout / "dem_dt20.npz")
    assert int(run["unstable"]) == 1
    assert 0.0 < float(run["unstable_at"]) < DURATION  # stopped before the scenario's end
    assert str(run["unstable_reason"])  # says why
    assert float(run["wall_s"]) > 0.0
    assert not any(key.startswith("field_") for key in run)


def test_stable_step_runs_to_the_end_with_its_fields(heldout):
    grid = doe.grid_of(tiny_config())
    ev._run_heldout_dem(heldout, "dem", grid, 0.0, 1.0, 0, None)
    run = ev.load_run(heldout / "dem.npz")
    assert int(run["unstable"]) == 0
    assert "unstable_at" not in run
    # one snapshot per second from t0, less the velocity window at the end
    assert run["field_mass"].shape[0] == DURATION + 1 - doe.VELOCITY_WINDOW
    assert run["out_mass"].sum() == pytest.approx(150.0 * DURATION, abs=200.0)


def test_instability_names_each_cause():
    from surrogate.dem import Dem

    dem = Dem(tiny_config())
    dem.place(np.array([[-1.0, 0.3], [1.0, 0.3]]), 100.0, 0.5, 1.0, doe.FEED_F, 1)
    assert doe.instability(dem) is None
    dem.pos[0] = [50.0, 1.0]
    assert "left the container" in doe.instability(dem)
    dem.pos[0] = [-1.0, 0.3]
    dem.vel[0] = [0.0, -200.0]
    assert "speed" in doe.instability(dem)
    dem.vel[0] = 0.0
    # a third disk nearly on top of the first: the overlap rule
    dem.place(np.array([[-1.0 + 0.1 * dem.radius[0], 0.3]]), 100.0, 0.5, 1.0, doe.FEED_F, 1)
    assert "overlap" in doe.instability(dem)


def test_a_run_with_config_changes_continues_the_same_pile_by_that_method(heldout):
    """The chart's nonsmooth points: the same start and feed, the method changed;
    it runs to the end at the paper's 11 ms and delivers what the feeder took
    (the feeder's set rate over the run, as the explicit run)."""
    grid = doe.grid_of(tiny_config())
    changes = {"method": "nonsmooth", "solver_iterations": 25}
    ev._run_heldout_dem(heldout, "dem_nonsmooth", grid, 0.0, 1.0, 0, None, changes=changes)
    run = ev.load_run(heldout / "dem_nonsmooth.npz")
    assert int(run["unstable"]) == 0
    assert float(run["dt"]) == 0.011
    assert run["field_mass"].shape[0] == DURATION + 1 - doe.VELOCITY_WINDOW
    assert run["out_mass"].sum() == pytest.approx(150.0 * DURATION, abs=200.0)
