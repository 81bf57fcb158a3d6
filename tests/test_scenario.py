"""Scenario files: validation with clear errors, and the simulate/reproduce command line."""

import copy
import json
import subprocess
import sys
from pathlib import Path

import pytest

from cosim.errors import ValidationError
from cosim.scenario import load, validate

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "step_response.toml"


def test_example_scenario_is_valid_and_validation_is_idempotent():
    config = load(EXAMPLE)
    assets = config["assets"]
    assert assets["left"]["grade"] == 0.2
    assert assets["right"]["grade"] == 0.8
    assert assets["crusher"]["parameters"]["gap_width"] == 0.25
    assert assets["stockpile"]["capacity_kg"] == 2.0e6
    assert assets["mill"]["speed_rad_s"] == 1.2
    assert validate(copy.deepcopy(config)) == config


def _broken(path, value):
    config = copy.deepcopy(load(EXAMPLE))
    *parents, key = path
    table = config
    for name in parents:
        table = table[name]
    if value is KeyError:
        del table[key]
    else:
        table[key] = value
    return config


BELT_IN = ("assets", "conveyor_crusher_stockpile")
BELT_OUT = ("assets", "conveyor_stockpile_mill")


@pytest.mark.parametrize("path, value, field, allowed", [
    (("assets", "left", "grade"), 1.5, "assets.left.grade", "<= 1"),
    (("assets", "left", "particle_mass_kg"), -5.0, "assets.left.particle_mass_kg", "> 0"),
    (("assets", "right", "hardness"), {"kind": "wobbly"}, "assets.right.hardness.kind",
     "one of"),
    (("simulation", "step_s"), 0.0, "simulation.step_s", ">= 0.001"),
    (("simulation", "until_s"), float("nan"), "simulation.until_s", "finite"),
    (("assets", "crusher", "speed_rad_s"), "fast", "assets.crusher.speed_rad_s", "a number"),
    (("assets", "crusher", "zone_capacity"), 900.0, "assets.crusher.zone_capacity",
     "one of ["),
    (("assets", "mill", "position_m"), KeyError, "assets.mill.position_m", "given"),
    (("assets", "mill", "kind"), "grinder", "assets.mill.kind", "one of ["),
    (("assets", "stockpile", "model"), "magic", "assets.stockpile.model", "one of"),
    (("assets", "stockpile", "outlets", "bottom", "discharge"), [[0.0, 0.0], [500.0, 3000.0]],
     "assets.stockpile.outlets.bottom.discharge[1].rate", "<= 2000 kg/s"),
    (("assets", "stockpile", "inlets", "top", "position_m"), [1.0],
     "assets.stockpile.inlets.top.position_m", "2 or 3"),
    ((*BELT_OUT, "length_m"), 0.0, "assets.conveyor_stockpile_mill.length_m", "> 0"),
    # sizes that set an allocation are bounded (each was a traceback or a memory error)
    (("assets", "left", "length_m"), 1e308, "assets.left.length_m", "<= 100000 m"),
    (("assets", "left", "block_length_m"), 1e-9, "assets.left.block_length_m",
     "(length_m / 1,000,000 blocks)"),
    (("assets", "left", "particle_mass_kg"), 1e-6, "assets.left.particle_mass_kg",
     "assets.trucks.trucks[0].payload_kg / 100,000 particles per load"),
    ((*BELT_IN, "length_m"), 1e308, "assets.conveyor_crusher_stockpile.length_m",
     "<= 100000 m"),
    ((*BELT_IN, "bin_length_m"), 1000.0, "assets.conveyor_crusher_stockpile.bin_length_m",
     "<= 120 m"),
    # ... and so is everything else that was silently accepted
    (("simulation", "seed"), 1.5, "simulation.seed", "an integer"),
    (("assets", "stockpile", "options"), {"bogus": 1}, "assets.stockpile.options.bogus",
     "no options"),
    (("assets", "crusher", "parameters"), {"gap_width": -0.25},
     "assets.crusher.parameters.gap_width", ">= 1e-06 m (the FMU's declared range)"),
    (("assets", "crusher", "parameters"), {"gap": 0.25}, "assets.crusher.parameters.gap",
     "'gap_width'"),
    # the wiring: flows name existing assets and ports
    (("flows",), [{"from": "crusher.product", "to": "belt.feed"}], "flows[0].to",
     "an asset among"),
    (("flows",), [{"from": "crusher.outlet", "to": "mill.feed"}], "flows[0].from",
     "an outlet of crusher (crusher): one of ['product']"),
    (("flows",), [{"from": "crusher.product", "to": "mill.side"}], "flows[0].to",
     "an inlet of mill (mill): one of ['feed']"),
    (("flows",), [{"from": "crusher.product", "to": "trucks.dump"}], "flows[0].to",
     "an inlet: trucks (truck_fleet) has none"),
    (("signals",), [{"from": "pump.rate", "to": "mill.speed"}], "signals[0].from",
     "an asset among"),
])
def test_bad_values_name_the_key_and_the_allowed_range(path, value, field, allowed):
    with pytest.raises(ValidationError) as error:
        validate(_broken(path, value))
    assert error.value.field == field
    assert allowed in str(error.value)


def test_truck_routes_must_name_sources():
    config = copy.deepcopy(load(EXAMPLE))
    config["assets"]["trucks"]["trucks"][0]["route"] = ["left", "middle"]
    with pytest.raises(ValidationError, match=r"trucks\[0\].route.*'left', 'right'"):
        validate(config)


def test_missing_or_malformed_files_are_clear_errors(tmp_path):
    with pytest.raises(ValidationError, match="not found"):
        load(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[simulation\nuntil_s = 3\n")
    with pytest.raises(ValidationError, match="valid TOML"):
        load(bad)


def _minetwin(*args):
    return subprocess.run([sys.executable, "-m", "minetwin.cli", *args], capture_output=True,
                          text=True, cwd=ROOT, timeout=300)


def test_simulate_command_writes_results(tmp_path):
    result = _minetwin("simulate", str(EXAMPLE), "--until", "60", "--out", str(tmp_path),
                       "--seed", "3", "--quiet")
    assert result.returncode == 0, result.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["simulated_s"] == 60.0 and summary["seed"] == 3
    assert summary["particles_created"] == 300          # two 15 t loads of ~100 kg
    assert summary["mass_balance_rel_error"] < 1e-9
    for name in ("timeseries.parquet", "events.sqlite", "overview.png"):
        assert (tmp_path / name).is_file()
        assert str(tmp_path / name) in result.stdout


def test_simulate_command_refuses_bad_input_with_exit_code_2(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(EXAMPLE.read_text().replace("grade = 0.2 ", "grade = 2.0 "))
    result = _minetwin("simulate", str(bad), "--out", str(tmp_path / "out"))
    assert result.returncode == 2
    assert "assets.left.grade: must be finite and >= 0 and <= 1" in result.stderr
    result = _minetwin("simulate", str(EXAMPLE), "--out", str(tmp_path / "out"),
                       "--storage-model", "magic")
    assert result.returncode == 2 and "--storage-model: must be one of" in result.stderr
    assert _minetwin("simulate", "--help").returncode == 0
    assert _minetwin("reproduce", "--help").returncode == 0


def test_one_validation_pass_reports_every_error_at_once():
    from cosim.errors import ValidationErrors

    config = copy.deepcopy(load(EXAMPLE))
    config["assets"]["left"]["grade"] = 1.5
    config["assets"]["mill"]["speed_rad_s"] = -1.0
    config["assets"]["crusher"]["jaw"] = 1.0
    config["simulation"]["step_s"] = 0.0
    config["flows"][1]["to"] = "conveyor_crusher_stockpile.side"
    with pytest.raises(ValidationErrors) as error:
        validate(config)
    fields = [e.field for e in error.value.errors]
    assert fields == ["simulation.step_s", "assets.left.grade", "assets.crusher.jaw",
                      "assets.mill.speed_rad_s", "flows[1].to"]
    message = str(error.value)
    assert "assets.mill.speed_rad_s: must be finite and >= 0 and <= 100 rad/s (got -1.0)" \
        in message
    assert "assets.crusher.jaw: must be one of ['fmu', 'jaw_throughput_kg_s'" in message
    assert len(message.splitlines()) == 5


def test_every_outlet_is_routed_and_split_fractions_add_up_to_one():
    config = copy.deepcopy(load(EXAMPLE))
    del config["flows"][3]                              # stockpile.bottom -> belt
    with pytest.raises(ValidationError, match="a flow from stockpile.bottom"):
        validate(config)
    config = copy.deepcopy(load(EXAMPLE))
    config["flows"][2]["fraction"] = 0.5
    config["flows"].append({"from": "conveyor_crusher_stockpile.out", "to": "stockpile.top",
                            "fraction": 0.25})
    with pytest.raises(ValidationError, match="fractions adding up to 1.*add up to 0.75"):
        validate(config)
