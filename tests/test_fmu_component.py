"""FmuComponent: interface validation with clear errors, parameters, a failing
doStep stopping the master with recorded data kept, and swapping the crusher
FMU by changing one path (jaw and cone crusher, FMI 3.0 and 2.0)."""

from __future__ import annotations

import numpy as np
import pytest

from cosim import sizes
from cosim.errors import ValidationError
from cosim.fmu import (CRUSHER_INTERFACE, MILL_INTERFACE, FmuCallError, FmuComponent,
                       FmuInterfaceError, VariableSpec, fmu_path)
from cosim.master import Component, CosimulationError, Master
from fmu_scenario import run_crusher_scenario


@pytest.fixture(scope="module", autouse=True)
def built_fmus():
    from fmus.build import build_all

    build_all()


@pytest.mark.parametrize("fmi", [3, 2])
@pytest.mark.parametrize("model", ["crusher", "cone_crusher"])
def test_swapping_crusher_fmu_by_path(model, fmi):
    series, zone = run_crusher_scenario(fmu_path(model, fmi))
    assert len(series) == 20
    torque = series["crusher_fmu.torque"].to_numpy()
    assert np.all(torque > 0)
    np.testing.assert_allclose(series["crusher_fmu.power"], 10.0 * torque, rtol=1e-12)
    np.testing.assert_allclose(series["crusher_fmu.energy"], np.cumsum(10.0 * torque * 0.5),
                               rtol=1e-12)
    # the fragmentation map conserves each passing particle's mass fractions
    np.testing.assert_allclose(zone.f.sum(axis=1), 1.0, rtol=1e-12)
    crushed = zone.f[:zone.passed]
    if model == "crusher":
        assert np.all(crushed[:, sizes.DIAMETERS >= 0.25] == 0.0)


def test_fmi2_and_fmi3_crusher_give_identical_series():
    fmi3, _ = run_crusher_scenario(fmu_path("crusher", 3))
    fmi2, _ = run_crusher_scenario(fmu_path("crusher", 2))
    np.testing.assert_array_equal(fmi3.to_numpy(), fmi2.to_numpy())


@pytest.mark.parametrize("fmi", [3, 2])
def test_missing_variable_names_file_and_variable(fmi):
    path = fmu_path("crusher", fmi)
    with pytest.raises(FmuInterfaceError) as info:
        FmuComponent(path, interface=MILL_INTERFACE)
    message = str(info.value)
    assert path.name in message and "'speed_setpoint'" in message and "missing" in message
    assert "input" in message


@pytest.mark.parametrize("fmi", [3, 2])
def test_wrong_causality_is_refused(fmi):
    spec = (VariableSpec("torque", "input"),)
    with pytest.raises(FmuInterfaceError, match=r"variable 'torque': must be an input .*"
                                                r"causality is 'output'"):
        FmuComponent(fmu_path("crusher", fmi), interface=spec)


@pytest.mark.parametrize("fmi", [3, 2])
def test_wrong_array_size_is_refused(fmi):
    spec = (VariableSpec("zone_hardness_mass", "input", (15,)),)
    with pytest.raises(FmuInterfaceError) as info:
        FmuComponent(fmu_path("crusher", fmi), interface=spec)
    message = str(info.value)
    assert "shape (15,)" in message and "shape (16,)" in message
    if fmi == 2:
        assert "zone_hardness_mass[1] .. zone_hardness_mass[15]" in message


def test_unknown_parameter_and_bad_parameter_value():
    with pytest.raises(ValidationError, match=r"crusher.fmu: parameter 'gap': must be one of "
                                              r"\['gap_width', 'k_oversize', 'k_undersize'\]"):
        FmuComponent(fmu_path("crusher"), parameters={"gap": 0.2})
    with pytest.raises(FmuCallError, match=r"crusher.fmu: exitInitializationMode failed: "
                                           r"gap_width = -1: must be finite and >= 1e-06 m"):
        FmuComponent(fmu_path("crusher"), parameters={"gap_width": -1.0})
    with pytest.raises(FmuCallError, match="open_side_width = 0.2 m: must be > gap_width"):
        FmuComponent(fmu_path("cone_crusher", 2),
                     parameters={"gap_width": 0.25, "open_side_width": 0.2})


def test_missing_fmu_file_says_how_to_build():
    with pytest.raises(ValidationError, match="run `minetwin fmus build`"):
        fmu_path("no_such_model")


def test_wrong_input_shape_is_refused():
    fmu = FmuComponent(fmu_path("crusher"), interface=CRUSHER_INTERFACE)
    try:
        with pytest.raises(ValidationError, match=r"zone_hardness_mass: must be an array of "
                                                  r"shape \(16,\) \(got shape \(3,\)\)"):
            fmu.set_input("zone_hardness_mass", np.ones(3))
        with pytest.raises(ValidationError, match="input: must be one of"):
            fmu.set_input("charge_mass", np.ones(16))
    finally:
        fmu.finish()


class BadFeed(Component):
    """Feeds a valid charge, then a negative mass from t = 2 s on."""

    name = "feed"

    def __init__(self):
        super().__init__()
        self.t = 0.0

    def step(self, t, dt):
        self.t = t + dt

    def outputs(self):
        charge = np.full(16, 100.0)
        if self.t > 2.0:
            charge[3] = -5.0
        return {"charge_mass": charge}


@pytest.mark.parametrize("fmi", [3, 2])
def test_failing_do_step_stops_master_and_keeps_data(fmi):
    master = Master(step=0.5, progress=False)
    feed = master.add(BadFeed())
    mill = master.add(FmuComponent(fmu_path("mill", fmi), interface=MILL_INTERFACE, name="mill"))
    master.connect(feed, "charge_mass", mill, "charge_mass")
    with pytest.raises(CosimulationError) as info:
        master.run(10.0)
    message = str(info.value)
    assert f"mill{'' if fmi == 3 else '-fmi2'}.fmu" in message
    assert "doStep at t = 2 s failed" in message
    assert "charge_mass[3] (0-based) = -5: must be finite and >= 0 kg" in message
    series = master.timeseries
    assert list(series.index) == [0.5, 1.0, 1.5, 2.0]
    assert np.all(series["mill.power"] > 0)
    master.finish()
    mill.finish()  # idempotent


def test_master_records_every_output_including_arrays():
    master = Master(step=1.0, progress=False)
    mill = master.add(FmuComponent(fmu_path("mill"), interface=MILL_INTERFACE, name="mill"))
    mill.set_input("charge_mass", np.full(16, 10.0))
    master.run(3.0)
    series = master.timeseries
    master.finish()
    for key in ("speed", "torque", "power", "d50", "torque_active"):
        assert f"mill.{key}" in series
    assert "mill.breakage_rate[15]" in series and "mill.escape_rate[0]" in series
    assert not any(c.startswith("mill.daughter_fraction") for c in series)


def test_fmu_state_get_set_restores_outputs():
    fmu = FmuComponent(fmu_path("mill"), interface=MILL_INTERFACE, parameters={"initial_speed": 0.0})
    try:
        fmu.set_input("charge_mass", np.full(16, 10.0))
        fmu.step(0.0, 1.0)
        state = fmu.slave.getFMUState()
        fmu.step(1.0, 1.0)
        after = fmu.outputs()["speed"]
        fmu.slave.setFMUState(state)
        fmu.step(1.0, 1.0)
        assert fmu.outputs()["speed"] == after
        fmu.slave.freeFMUState(state)
    finally:
        fmu.finish()


def test_cli_build_and_validate(capsys):
    from minetwin.cli import main

    assert main(["fmus", "build", "--model", "crusher"]) == 0
    assert "up to date" in capsys.readouterr().err
    path = str(fmu_path("crusher"))
    assert main(["fmus", "validate", path]) == 0
    assert "ok" in capsys.readouterr().out
    assert main(["fmus", "validate", "--interface", "mill", path]) == 1
    assert "variable 'speed_setpoint': must be an input" in capsys.readouterr().err
    assert main(["fmus", "validate", "no/such.fmu"]) == 2
    assert main(["fmus", "build", "--model", "ball_mill"]) == 2


def test_fmu_from_other_sources_is_refused_at_instantiation(tmp_path):
    import zipfile

    source = fmu_path("crusher")
    corrupted = tmp_path / "stale_crusher.fmu"
    with zipfile.ZipFile(source) as src, zipfile.ZipFile(corrupted, "w") as dst:
        for item in src.infolist():
            data = src.read(item)
            if item.filename == "modelDescription.xml":
                data = data.replace(b'instantiationToken="{', b'instantiationToken="{0')
            dst.writestr(item, data)
    with pytest.raises(FmuCallError, match="stale_crusher.fmu: instantiate failed: "
                                           "instantiationToken does not match"):
        FmuComponent(corrupted, interface=CRUSHER_INTERFACE)


def test_step_after_finish_is_an_error_not_a_crash():
    fmu = FmuComponent(fmu_path("crusher"), interface=CRUSHER_INTERFACE)
    fmu.finish()
    with pytest.raises(FmuCallError, match="crusher.fmu: step after finish"):
        fmu.step(0.0, 0.5)
