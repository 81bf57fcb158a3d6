"""The master with FMUs beyond the crusher/mill convention, each case in FMI 3.0
and FMI 2.0 and compared with ``fmpy.simulate_fmu`` on the same FMU, step and
inputs (the maximum absolute difference is printed; 0 where the arithmetic is
the same): a stop request, every variable type, an event inside a
communication step. The FMUs are our own test models (tests/fmus/)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from fmpy import simulate_fmu

from cosim.errors import ValidationError
from cosim.fmu import FmuComponent, FmuInterfaceError, VariableSpec, describe_fmu
from cosim.master import Master
from fmus.typed import typed_fmu_file


@pytest.fixture(scope="module", autouse=True)
def built_fmus():
    from fmus.build import build_all

    build_all(names=())


def reference(path, fmi, *, step, stop_time, **options):
    """fmpy's own simulation loop (FMI 3: early return, and event mode where the FMU has
    it, as the master)."""
    if fmi == 3:
        options.update(use_event_mode=describe_fmu(path)["event_mode"], early_return_allowed=True)
    return simulate_fmu(str(path), stop_time=stop_time, output_interval=step, **options)


def on_times(result, times):
    """fmpy's rows at ``times`` (the last row where an event repeats a time)."""
    rows = {}
    for row in result:
        rows[float(row["time"])] = row
    return np.array([rows[t] for t in times], dtype=result.dtype)


def max_abs_difference(ours, theirs) -> float:
    return float(np.max(np.abs(np.asarray(ours, dtype=np.float64)
                               - np.asarray(theirs, dtype=np.float64))))


def run_alone(path, until, step=0.5, parameters=None, inputs=()):
    master = Master(step=step, progress=False)
    fmu = master.add(FmuComponent(path, name="fmu", parameters=parameters))
    for name, value in dict(inputs).items():
        fmu.set_input(name, value)
    master.run(until)
    series = master.timeseries
    master.finish()
    return master, fmu, series


# ---- stop requests -----------------------------------------------------------------------
@pytest.mark.parametrize("fmi", [3, 2])
@pytest.mark.parametrize("stop_time", [9.0, 9.25])
def test_stop_request_ends_the_run_at_the_fmus_time(fmi, stop_time):
    path = typed_fmu_file("counter", fmi)
    master, fmu, series = run_alone(path, 20.0, parameters={"stop_time": stop_time})
    assert master.stopped["component"] == "fmu"
    assert master.stopped["time"] == stop_time == master.time == series.index[-1]
    assert path.name in master.stopped["reason"]
    assert ("terminateSimulation" if fmi == 3 else "fmi2Terminated") in master.stopped["reason"]
    assert series["fmu.counter"].dtype == np.int32
    assert series["fmu.counter"].iloc[-1] == 9
    np.testing.assert_array_equal(series.index[:-1],
                                  np.arange(1, int(np.ceil(stop_time / 0.5))) * 0.5)

    theirs = reference(path, fmi, step=0.5, stop_time=20.0, start_values={"stop_time": stop_time})
    assert theirs["time"][-1] == stop_time  # fmpy stops at the same time
    matched = on_times(theirs, list(series.index))
    for column in ("counter", "elapsed"):
        difference = max_abs_difference(series[f"fmu.{column}"], matched[column])
        print(f"FMI {fmi} stop at {stop_time}: max |master - fmpy| of {column} = {difference}")
        assert difference == 0.0
    with pytest.raises(ValidationError, match="not past the stop requested by fmu at"):
        master.run(30.0)


def test_stopped_names_the_component_the_time_and_the_fmi_status():
    master = Master(step=1.0, progress=False)
    master.add(FmuComponent(typed_fmu_file("counter", 2), name="stair",
                            parameters={"stop_time": 3.0}))
    master.run(10.0)
    master.finish()
    assert master.stopped == {"component": "stair", "time": 3.0,
                              "reason": "counter-fmi2.fmu requested to terminate the simulation "
                                        "(fmi2DoStep returned fmi2Discard, fmi2Terminated = true)"}


# ---- every variable type -----------------------------------------------------------------
PARAMETERS = {  # within each type's range, through the sums too
    "p_float32": 1.5, "p_float64": 2.5, "p_int8": -100, "p_uint8": 200, "p_int16": -30000,
    "p_uint16": 60000, "p_int32": -2000000000, "p_uint32": 4000000000,
    "p_int64": -9000000000000000000, "p_uint64": 18000000000000000000, "p_boolean": True,
    "p_string": "gap=", "p_binary": "0a0b", "p_enumeration": "high"}
INPUTS = {
    "u_float32": 0.1, "u_float64": 0.5, "u_int8": 27, "u_uint8": 55, "u_int16": 2767,
    "u_uint16": 5535, "u_int32": 147483647, "u_uint32": 294967295, "u_int64": -223372036854775808,
    "u_uint64": 446744073709551615, "u_boolean": True, "u_string": "0.25 m",
    "u_binary": b"\xff\x00", "u_enumeration": 2,
    "u_int32_array": np.array([5, -7, 11], dtype=np.int32), "u_boolean_array": [False, True]}
ENUMERATION = {"off": 1, "low": 2, "high": 3}


def expected_outputs(fmi, time):
    p = {k: ENUMERATION.get(v, v) if k == "p_enumeration" else v for k, v in PARAMETERS.items()}
    y = {"y_float64": p["p_float64"] + INPUTS["u_float64"] * time,
         "y_int32": p["p_int32"] + INPUTS["u_int32"],
         "y_boolean": p["p_boolean"] != INPUTS["u_boolean"],
         "y_string": p["p_string"] + INPUTS["u_string"],
         "y_enumeration": (INPUTS["u_enumeration"] + p["p_enumeration"] - 2) % 3 + 1,
         "y_int32_array": 2 * INPUTS["u_int32_array"] + p["p_int32"],
         "y_boolean_array": ~np.array(INPUTS["u_boolean_array"])}
    if fmi == 3:
        y["y_float32"] = float(np.float32(p["p_float32"]) + np.float32(INPUTS["u_float32"]))
        y["y_binary"] = bytes.fromhex(p["p_binary"]) + INPUTS["u_binary"]
        for kind in ("int8", "uint8", "int16", "uint16", "uint32", "int64", "uint64"):
            y[f"y_{kind}"] = p[f"p_{kind}"] + INPUTS[f"u_{kind}"]
    return y


def _for(fmi, values):
    available = {v["name"] for v in describe_fmu(typed_fmu_file("all_types", fmi))["variables"]}
    return {k: v for k, v in values.items() if k in available}


@pytest.mark.parametrize("fmi", [3, 2])
def test_every_variable_type_is_read_recorded_and_written(fmi):
    path = typed_fmu_file("all_types", fmi)
    parameters, inputs = _for(fmi, PARAMETERS), _for(fmi, INPUTS)
    master, fmu, series = run_alone(path, 2.0, parameters=parameters, inputs=inputs)
    for name, value in expected_outputs(fmi, 2.0).items():
        if np.ndim(value):  # arrays: numpy arrays of the type, recorded as name[k] columns
            assert np.array_equal(fmu.outputs()[name], value), name
            assert fmu.outputs()[name].dtype == value.dtype, name
            recorded = [series[f"fmu.{name}[{k}]"].iloc[-1] for k in range(len(value))]
            assert np.array_equal(recorded, value), name
            continue
        recorded = series[f"fmu.{name}"].iloc[-1]
        assert recorded == value and type(fmu.outputs()[name]) is type(value), name
    dtypes = {"y_int32": np.int32, "y_boolean": np.bool_, "y_enumeration": np.int64,
              "y_int32_array[2]": np.int32, "y_boolean_array[1]": np.bool_}
    if fmi == 3:
        dtypes.update(y_uint64=np.uint64, y_int64=np.int64, y_int8=np.int8, y_float32=np.float32)
    for name, dtype in dtypes.items():
        assert series[f"fmu.{name}"].dtype == dtype, name
    assert series["fmu.y_uint64" if fmi == 3 else "fmu.y_int32"].iloc[-1] == \
        expected_outputs(fmi, 0)["y_uint64" if fmi == 3 else "y_int32"]  # exact, no float
    assert fmu.item_name("y_enumeration", 3) == "high"
    assert fmu.variables["y_enumeration"].items == {1: "off", 2: "low", 3: "high"}

    # fmpy with the same parameters and inputs (as start values) on the same step
    start_values = {**{k: ENUMERATION.get(v, v) if k == "p_enumeration" else v
                       for k, v in parameters.items()}, **inputs}
    for name in ("u_int32_array", "u_boolean_array"):  # fmpy: lists; FMI 2: the elements
        values = [x.item() if hasattr(x, "item") else x for x in start_values.pop(name)]
        start_values.update({name: values} if fmi == 3 else
                            {f"{name}[{k + 1}]": x for k, x in enumerate(values)})
    if fmi == 3:  # fmpy takes Binary start values as hex text
        start_values["u_binary"] = inputs["u_binary"].hex()
    theirs = reference(path, fmi, step=0.5, stop_time=2.0, start_values=start_values)
    matched = on_times(theirs, list(series.index))
    compared = [n for n in theirs.dtype.names if n != "time"]
    assert len(compared) == (14 if fmi == 3 else 9)  # fmpy records numbers and Booleans
    for name in compared:
        if theirs[name].ndim == 2:  # an FMI 3 array: our columns name[0]..
            ours = np.stack([series[f"fmu.{name}[{k}]"] for k in range(theirs[name].shape[1])],
                            axis=1)
        else:  # FMI 2 elements name[1].. are our name[0]..
            element = re.match(r"^(.+)\[(\d+)\]$", name)
            column = f"{element[1]}[{int(element[2]) - 1}]" if element else name
            ours = series[f"fmu.{column}"].to_numpy()
        if ours.dtype.kind in "iub":  # integers compared exactly, not through floats
            assert np.array_equal(ours, matched[name]), name
            difference = 0 if np.array_equal(ours, matched[name]) else None
        else:
            difference = max_abs_difference(ours, matched[name])
        print(f"FMI {fmi}: max |master - fmpy| of {name} = {difference}")
        assert difference == 0.0


@pytest.mark.parametrize("fmi", [3, 2])
def test_inputs_and_parameters_are_type_checked(fmi):
    fmu = FmuComponent(typed_fmu_file("all_types", fmi))
    try:
        refusals = [("u_int32", 1.5, "Int32 integer in -2147483648..2147483647"),
                    ("u_int32", 2 ** 31, "Int32 integer in -2147483648..2147483647"),
                    ("u_boolean", 1, r"a Boolean \(True or False\)"),
                    ("u_string", 5, "a String"),
                    ("u_float64", "1.0", "a Float64 number"),
                    ("u_enumeration", "medium", "one of the items"),
                    ("u_enumeration", 4, "one of the items")]
        refusals += [("u_int32_array", [1, 2, 2 ** 40], "Int32 integer in"),
                     ("u_int32_array", [1, 2], r"an array of shape \(3,\)"),
                     ("u_boolean_array", [1, 0], "a Boolean")]
        if fmi == 3:
            refusals += [("u_int8", 200, "Int8 integer in -128..127"),
                         ("u_uint64", -1, "UInt64 integer in 0..18446744073709551615"),
                         ("u_binary", "ff", r"Binary \(bytes\)")]
        for name, value, message in refusals:
            with pytest.raises(ValidationError, match=f"{name}: must be (an? )?{message}"):
                fmu.set_input(name, value)
        fmu.set_input("u_enumeration", "high")
        fmu.step(0.0, 1.0)
        assert fmu.outputs()["y_enumeration"] == 1  # (3 + 2 - 2) % 3 + 1
    finally:
        fmu.finish()
    with pytest.raises(ValidationError, match="p_int32: must be an Int32 integer"):
        FmuComponent(typed_fmu_file("all_types", fmi), parameters={"p_int32": "7"})
    with pytest.raises(ValidationError, match="p_boolean: must be a Boolean"):
        FmuComponent(typed_fmu_file("all_types", fmi), parameters={"p_boolean": 1})


def test_non_float_outputs_connect_to_inputs_of_their_type():
    """An Int32 output drives an Int32 input; a Boolean output a Boolean input."""
    master = Master(step=1.0, progress=False)
    stair = master.add(FmuComponent(typed_fmu_file("counter", 3), name="stair",
                                    parameters={"stop_time": 100.0}))
    typed = master.add(FmuComponent(typed_fmu_file("all_types", 2), name="typed"))
    master.connect(stair, "counter", typed, "u_int32")
    master.run(5.0)
    series = master.timeseries
    master.finish()
    np.testing.assert_array_equal(series["typed.y_int32"] - series["stair.counter"],
                                  np.full(5, -2000000000))
    assert series["typed.y_int32"].dtype == np.int32
    other = Master(step=1.0, progress=False)
    stair = other.add(FmuComponent(typed_fmu_file("counter", 2), name="stair"))
    typed = other.add(FmuComponent(typed_fmu_file("all_types", 3), name="typed"))
    other.connect(stair, "counter", typed, "u_float64")  # an Int32 feeds a Float64
    for output, input, kind in (("elapsed", "u_int32", "Float64"), ("counter", "u_boolean",
                                                                     "Int32"),
                                ("counter", "u_string", "Int32")):
        with pytest.raises(ValidationError, match=f"connect stair.{output} -> typed.{input}: "
                                                  f"must be an output an? .* input takes "
                                                  f"\\(stair.{output} is {kind}\\)"):
            other.connect(stair, output, typed, input)
    other.finish()


@pytest.mark.parametrize("fmi", [3, 2])
def test_mistyped_variables_are_listed_with_their_types(fmi):
    spec = (VariableSpec("y_int32", "output"), VariableSpec("y_boolean", "output"),
            VariableSpec("y_float64", "output"), VariableSpec("y_string", "output", type="String"))
    with pytest.raises(FmuInterfaceError) as info:
        FmuComponent(typed_fmu_file("all_types", fmi), interface=spec)
    message = str(info.value)
    native = "Integer" if fmi == 2 else "Int32"
    assert message.startswith(f"all_types{'-fmi2' if fmi == 2 else ''}.fmu: 2 variables do not "
                              "match the interface: ")
    assert f"variable 'y_int32': must be an output Float64 variable, a scalar (its type is " \
           f"{native})" in message
    assert "variable 'y_boolean': must be an output Float64 variable, a scalar (its type is " \
           "Boolean)" in message


# ---- an event inside a communication step --------------------------------------------------
@pytest.mark.parametrize("fmi", [3, 2])
@pytest.mark.parametrize("rate", [0.8, 0.7])
def test_event_inside_a_step_as_fmpy_handles_it(fmi, rate):
    path = typed_fmu_file("level_event", fmi)
    master, fmu, series = run_alone(path, 6.0, inputs={"rate": rate})
    # events at k / rate s: with 0.8 at 1.25 (inside [1.0, 1.5]), 2.5 (a step's end), 3.75, 5.0
    events = int(np.floor(6.0 * rate + 1e-9))
    assert series["fmu.resets"].iloc[-1] == events
    assert fmu.events_handled == (events if fmi == 3 else 0)  # FMI 2: inside doStep
    assert np.all((series["fmu.level"] >= 0.0) & (series["fmu.level"] < 1.0))

    theirs = reference(path, fmi, step=0.5, stop_time=6.0, start_values={"rate": rate})
    matched = on_times(theirs, list(series.index))
    assert np.array_equal(series["fmu.resets"], matched["resets"])
    difference = max_abs_difference(series["fmu.level"], matched["level"])
    print(f"FMI {fmi} rate {rate}: max |master - fmpy| of level = {difference}")
    assert difference == 0.0
    exact = np.mod(rate * series.index.to_numpy(), 1.0)
    print(f"FMI {fmi} rate {rate}: max |master - (rate t mod 1)| = "
          f"{max_abs_difference(series['fmu.level'], exact)}")


# ---- minetwin fmus info ---------------------------------------------------------------------
@pytest.mark.parametrize("fmi", [3, 2])
def test_cli_info_lists_every_variable(fmi, capsys):
    import json

    from minetwin.cli import main
    from cosim.fmu import fmu_path

    path = typed_fmu_file("all_types", fmi)
    assert main(["fmus", "info", str(path)]) == 0
    text = capsys.readouterr().out
    assert f"FMI version      {fmi}.0" in text and "MineTwin fmus/typed.py" in text
    assert "(1 = off, 2 = low, 3 = high)" in text
    rows = {line.split()[0]: line.split() for line in text.splitlines()[10:]}
    assert rows["p_int32"][:4] == ["p_int32", "parameter", "Int32", "-2000000000"]
    assert rows["y_boolean"][:3] == ["y_boolean", "output", "Boolean"]
    if fmi == 3:
        assert rows["u_uint64"][:3] == ["u_uint64", "input", "UInt64"]
        assert rows["p_binary"][:4] == ["p_binary", "parameter", "Binary", "0a0b"]
    assert main(["fmus", "info", "--json", str(fmu_path("mill", fmi))]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["generation_tool"] == "MineTwin fmus/build.py"
    assert info["generation_date"].endswith("Z") and info["generation_date"][:2] == "20"
    charge = next(v for v in info["variables"] if v["name"] == "charge_mass")
    assert charge == {"name": "charge_mass", "causality": "input", "type": "Float64",
                      "native_type": "Float64" if fmi == 3 else "Real", "shape": [16],
                      "unit": "kg", "start": "0.0 (each element)",
                      "description": charge["description"], "items": {}}


@pytest.mark.parametrize("fmi", [3, 2])
def test_parameters_of_every_type_from_a_scenario_table(fmi):
    """A scenario's [assets.crusher.parameters] table (TOML) keeps each value's type for
    the FMU."""
    import tomllib

    from cosim.params import FmuParameters, Parameters, check

    class Table(Parameters):
        parameters: FmuParameters = {}

    def _parameters(table, path):
        checked, errors = check(Table, table, path)
        if errors:
            raise errors[0]
        return checked.parameters

    text = "\n".join(["[parameters]", 'p_string = "gap="', "p_boolean = true",
                      "p_int32 = -2000000000", "p_float64 = 2.5", 'p_enumeration = "high"']
                     + (["p_int8 = -100", "p_uint16 = 60000", 'p_binary = "0a0b"',
                         "p_float32 = 1.5"] if fmi == 3 else []))
    parameters = _parameters(tomllib.loads(text), "crusher")
    fmu = FmuComponent(typed_fmu_file("all_types", fmi), parameters=parameters)
    try:
        fmu.step(0.0, 1.0)
        outputs = fmu.outputs()
        assert outputs["y_string"] == "gap=0.25 m" and outputs["y_boolean"] is True
        assert outputs["y_int32"] == -2000000000 + 100000000
        assert outputs["y_enumeration"] == (1 + 3 - 2) % 3 + 1
        if fmi == 3:
            assert outputs["y_int8"] == -100 + 20 and outputs["y_binary"] == b"\x0a\x0b\xff"
    finally:
        fmu.finish()
    with pytest.raises(ValidationError, match="crusher.parameters.p_float64: must be a finite"):
        _parameters(tomllib.loads("[parameters]\np_float64 = nan"), "crusher")
    with pytest.raises(ValidationError, match="p_binary: must be Binary: bytes or a hex string"):
        FmuComponent(typed_fmu_file("all_types", 3), parameters={"p_binary": "xyz"})


def test_plant_run_stopped_by_an_fmu_says_so_in_its_summary(tmp_path):
    """The example plant with a stair counter added: the run ends at 5 s, the summary says why."""
    import json
    from pathlib import Path

    from cosim.scenario import build, load, summarize, write_outputs

    example = Path(__file__).resolve().parents[1] / "examples" / "step_response.toml"
    simulation = build(load(example), progress=False)
    simulation.master.add(FmuComponent(typed_fmu_file("counter", 3), name="stair",
                                       parameters={"stop_time": 5.0}))
    try:
        simulation.run(until=20.0)
        summary = summarize(simulation)
        assert summary["simulated_s"] == 5.0 and simulation.timeseries.index[-1] == 5.0
        assert summary["stopped_by"] == {
            "component": "stair", "time": 5.0,
            "reason": "counter.fmu requested to terminate the simulation "
                      "(fmi3DoStep terminateSimulation)"}
        written = write_outputs(simulation, tmp_path)
        assert json.loads((tmp_path / "summary.json").read_text())["stopped_by"] == \
            written["stopped_by"]
        assert simulation.timeseries["stair.counter"].dtype == np.int32
    finally:
        simulation.close()
