"""minetwin.testing.scenario without running the simulator: overrides and the run's checks."""

import numpy as np
import pandas as pd
import pytest

from cosim.errors import ValidationError
from minetwin.testing.scenario import ScenarioRun, apply_overrides

DOCUMENT = {"simulation": {"until_s": 300.0},
            "assets": {"crusher": {"kind": "crusher", "fmu": "crusher",
                                   "parameters": {"gap_width": 0.25}},
                       "mill": {"kind": "mill"}}}


def test_overrides_set_dotted_keys_on_a_copy():
    changed = apply_overrides(DOCUMENT, {"assets.crusher.fmu": "cone_crusher",
                                         "assets.crusher.parameters.gap_width": 0.2})
    crusher = changed["assets"]["crusher"]
    assert crusher["fmu"] == "cone_crusher"
    assert crusher["parameters"]["gap_width"] == 0.2
    assert DOCUMENT["assets"]["crusher"]["fmu"] == "crusher"   # the original is untouched


def test_an_override_through_a_missing_table_names_the_tables_there():
    with pytest.raises(ValidationError) as info:
        apply_overrides(DOCUMENT, {"assets.crushr.fmu": "cone_crusher"})
    message = str(info.value)
    assert "overrides['assets.crushr.fmu']" in message and "no table 'assets.crushr'" in message
    assert "['crusher', 'mill']" in message


def _run(errors, summary):
    frame = pd.DataFrame({"plant.mass_balance_rel_error": errors},
                         index=pd.Index(np.arange(1.0, len(errors) + 1), name="time"))
    return ScenarioRun(timeseries=frame, events=None, summary=summary, out=None, config={})


def test_run_mass_balance_checks_the_summary_and_every_recorded_time():
    good = {"mass_in_kg": 1000.0, "mass_held_kg": 600.0, "mass_out_kg": 400.0}
    assert _run([0.0, 1e-16, 2e-16], good).assert_mass_balance() == 2e-16
    with pytest.raises(AssertionError) as info:
        _run([0.0, 3e-6, 1e-16], good).assert_mass_balance()
    assert str(info.value).startswith("mass balance of the plant broken at t = 2 s: "
                                      "relative error 3e-06 > rtol 1e-09")
    with pytest.raises(AssertionError, match="100 kg lost"):
        _run([0.0], dict(good, mass_out_kg=300.0)).assert_mass_balance()
