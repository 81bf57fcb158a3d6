"""Co-simulation regression tests of a small plant: copy this folder and adapt.

Run:  pytest examples/cosim_tests                       (the plant as designed)
      pytest examples/cosim_tests --crusher cone_crusher   (after swapping the crusher FMU)
      pytest examples/cosim_tests --minetwin-record     (re-record the reference, then review)
"""

from pathlib import Path

import pytest

HERE = Path(__file__).parent
SCENARIO = HERE / "plant.toml"
REFERENCE = HERE / "plant_reference.csv"   # minetwin reference record plant.toml --out ...


def test_crusher_fmu_offers_what_the_crusher_asset_needs(load_fmu, crusher_fmu):
    crusher = load_fmu(crusher_fmu, interface="crusher")
    crusher.set_input("speed", 10.0)
    crusher.step(0.0, 0.5)
    assert crusher.outputs()["fragmentation_map"].shape == (16, 16)


def test_plant_conserves_mass_and_ids_and_matches_its_reference(run_scenario, reference_check,
                                                                crusher_fmu):
    run = run_scenario(SCENARIO, overrides={"crusher.fmu": crusher_fmu})
    run.assert_mass_balance()
    run.assert_particle_ids_accounted()
    reference_check(run.timeseries, REFERENCE, scenario=SCENARIO)


@pytest.mark.cosim
def test_stockpile_exchange_over_opcua_in_lockstep(mock_800xa, stockpile_client):
    stockpile = stockpile_client(model="mixing", seed=3, period=2.0)
    result = stockpile.run(until=60.0)
    assert result.time_s == pytest.approx(60.0)       # the server followed the client
    result.assert_mass_balance()
    result.assert_ids_accounted()
