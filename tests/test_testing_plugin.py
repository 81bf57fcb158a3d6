"""The minetwin pytest plugin as a user sees it: user test files run by pytester."""

pytest_plugins = ["pytester"]

USER_TEST = '''
import numpy as np
import pandas as pd

SCALE = {scale}

def test_power_matches_reference(reference_check):
    t = np.arange(0.0, 60.0, 0.5)
    frame = pd.DataFrame({{"crusher.power": SCALE * (1500 + 300 * np.sin(t / 5)),
                          "mill.power": 2.0e5 + 0 * t}}, index=pd.Index(t, name="time"))
    reference_check(frame, "power_ref.csv", scenario="scenario.toml")
'''

SCENARIO = '''
[reference]
signals = ["crusher.power", "mill.power"]
rtol = 0.02
time_shift = 1.0
'''


def _user_folder(pytester, scale):
    pytester.makefile(".toml", scenario=SCENARIO)
    pytester.makepyfile(test_user=USER_TEST.format(scale=scale))


def test_plugin_is_registered_and_lists_its_options(pytester):
    result = pytester.runpytest("--help")
    result.stdout.fnmatch_lines(["*--minetwin-record*", "*--minetwin-plots=DIR*"])
    header = pytester.runpytest("--co", "-q")
    header.stdout.no_fnmatch_line("*PluginValidationError*")


def test_reference_check_records_then_passes_then_catches_a_change(pytester):
    _user_folder(pytester, scale=1.0)
    pytester.runpytest("--minetwin-record").assert_outcomes(passed=1)
    csv = (pytester.path / "power_ref.csv").read_text().splitlines()
    assert csv[0] == "time,crusher.power,mill.power" and len(csv) == 121
    pytester.runpytest().assert_outcomes(passed=1)

    _user_folder(pytester, scale=1.05)                 # 5 % more power: outside 2 %
    plots = pytester.path / "plots"
    result = pytester.runpytest(f"--minetwin-plots={plots}")
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines([
        "*result differs from the reference*power_ref.csv*",
        "*signal*worst deviation*at t [[]s]*band there*outside*result*",
        "*crusher.power*FAIL*",
        "*mill.power*+0*pass*",
        "*1 of 2 signal(s) outside their band*",
    ])
    overlays = list(plots.rglob("*.png"))
    assert [p.name for p in overlays] == ["crusher.power.png"]


BROKEN_FMU_TEST = '''
import shutil
import zipfile

import pytest

from cosim.fmu import fmu_path

SCENARIO = {scenario!r}


def _without_power(tmp_path):
    """The crusher FMU whose output 'power' was renamed: the asset's variable is missing."""
    broken = tmp_path / "broken_crusher.fmu"
    with zipfile.ZipFile(fmu_path("crusher")) as source, zipfile.ZipFile(broken, "w") as target:
        for item in source.infolist():
            data = source.read(item)
            if item.filename == "modelDescription.xml":
                data = data.replace(b'name="power"', b'name="power_w"')
            target.writestr(item, data)
    return broken


def test_load_broken_crusher(load_fmu, tmp_path):
    load_fmu(_without_power(tmp_path), interface="crusher")


def test_run_plant_with_broken_crusher(run_scenario, tmp_path):
    run_scenario(SCENARIO, until=10.0, overrides={{"assets.crusher.fmu": str(_without_power(tmp_path))}})
'''


def test_a_broken_fmu_is_caught_at_load_naming_file_and_variable(pytester):
    from pathlib import Path

    scenario = Path(__file__).resolve().parent.parent / "examples" / "cosim_tests" / "plant.toml"
    pytester.makepyfile(test_user=BROKEN_FMU_TEST.format(scenario=str(scenario)))
    result = pytester.runpytest()
    result.assert_outcomes(failed=2)
    expected = ("*FmuInterfaceError: broken_crusher.fmu: variable 'power': must be an output "
                "Float64 variable, a scalar (missing)")
    result.stdout.fnmatch_lines(["*test_load_broken_crusher*", expected,
                                 "*test_run_plant_with_broken_crusher*", expected])
