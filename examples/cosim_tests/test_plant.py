"""Co-simulation regression tests of a small plant: copy this folder and adapt.

Run:  pytest examples/cosim_tests                          (the plant as designed)
      pytest examples/cosim_tests --crusher cone_crusher   (after swapping the crusher FMU)
      pytest examples/cosim_tests --minetwin-record        (re-record the reference, then review)
"""

from pathlib import Path

import pytest

from minetwin.testing import assert_step_response, signal_from

HERE = Path(__file__).parent
SCENARIO = HERE / "plant.toml"
REFERENCE = HERE / "plant_reference.csv"   # minetwin reference record plant.toml --out ...

pytestmark = pytest.mark.cosim              # select with -m cosim (marker of the minetwin plugin)


def test_crusher_fmu_offers_what_the_crusher_asset_needs(load_fmu, crusher_fmu):
    crusher = load_fmu(crusher_fmu, interface="crusher")
    crusher.set_input("speed", 10.0)
    crusher.step(0.0, 0.5)
    assert crusher.outputs()["fragmentation_map"].shape == (16, 16)


def test_plant_conserves_mass_and_particle_ids(plant_run):
    plant_run.assert_mass_balance()             # at every recorded time, rel. error <= 1e-9
    plant_run.assert_particle_ids_accounted()   # every particle in the plant or gone, once


def test_plant_matches_its_reference(plant_run, reference_check):
    # the reference covers 0-300 s; later samples of the run are not judged
    reference_check(plant_run.timeseries, REFERENCE, scenario=SCENARIO)


def test_crusher_power_steps_up_when_the_truck_reaches_harder_ore(plant_run):
    # plant.toml: the left source's hardness steps 1 -> 2 where the truck loads at 350 s
    time, power = signal_from(plant_run.timeseries, "crusher_fmu.power")
    assert_step_response(time, power, step_time=350.0, before=(130.0, 350.0),
                         after=(460.0, 700.0), smoothing=55.0,   # one truck cycle
                         ratio=(1.25, 1.55),      # paper: +40 % (1.5 -> 2.1 kW)
                         delay=(10.0, 60.0),      # hard ore must be loaded and hauled first
                         name="crusher_fmu.power")


def test_stockpile_exchange_over_opcua_in_lockstep(mock_800xa, stockpile_client):
    stockpile = stockpile_client(model="mixing", seed=3, period=2.0)
    result = stockpile.run(until=60.0)
    assert result.time_s == pytest.approx(60.0)       # the server followed the client
    result.assert_mass_balance()
    result.assert_ids_accounted()
