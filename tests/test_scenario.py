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
    assert config["sources"]["left"]["grade"] == 0.2
    assert config["sources"]["right"]["grade"] == 0.8
    assert config["crusher"]["parameters"]["gap_width"] == 0.25
    assert config["stockpile"]["capacity_kg"] == 2.0e6
    assert config["mill"]["speed_rad_s"] == 1.2
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


@pytest.mark.parametrize("path, value, field, allowed", [
    (("sources", "left", "grade"), 1.5, "sources.left.grade", "<= 1"),
    (("sources", "left", "particle_mass_kg"), -5.0, "sources.left.particle_mass_kg", "> 0"),
    (("sources", "right", "hardness"), {"kind": "wobbly"}, "sources.right.hardness.kind",
     "one of"),
    (("simulation", "step_s"), 0.0, "simulation.step_s", ">= 0.001"),
    (("simulation", "until_s"), float("nan"), "simulation.until_s", "finite"),
    (("crusher", "speed_rad_s"), "fast", "crusher.speed_rad_s", "a number"),
    (("crusher", "zone_capacity"), 900.0, "crusher.zone_capacity", "one of"),
    (("mill",), KeyError, "mill", "given"),
    (("stockpile", "model"), "magic", "stockpile.model", "one of"),
    (("stockpile", "discharge"), [[0.0, 0.0], [500.0, 3000.0]], "stockpile.discharge[1].rate",
     "<= 2000 kg/s"),
    (("stockpile", "position_m"), [1.0], "stockpile.position_m", "2 or 3"),
    (("conveyors", "stockpile_to_mill", "length_m"), 0.0,
     "conveyors.stockpile_to_mill.length_m", "> 0"),
    # sizes that set an allocation are bounded (each was a traceback or a memory error)
    (("sources", "left", "length_m"), 1e308, "sources.left.length_m", "<= 100000 m"),
    (("sources", "left", "block_length_m"), 1e-9, "sources.left.block_length_m",
     "(length_m / 1,000,000 blocks)"),
    (("sources", "left", "particle_mass_kg"), 1e-6, "sources.left.particle_mass_kg",
     "trucks[0].payload_kg / 100,000 particles per load"),
    (("conveyors", "crusher_to_stockpile", "length_m"), 1e308,
     "conveyors.crusher_to_stockpile.length_m", "<= 100000 m"),
    (("conveyors", "crusher_to_stockpile", "bin_length_m"), 1000.0,
     "conveyors.crusher_to_stockpile.bin_length_m", "<= 120 m"),
    # ... and so is everything else that was silently accepted
    (("simulation", "seed"), 1.5, "simulation.seed", "an integer"),
    (("stockpile", "options"), {"bogus": 1}, "stockpile.options.bogus", "no options"),
    (("crusher", "parameters"), {"gap_width": -0.25}, "crusher.parameters.gap_width",
     ">= 1e-06 m (the FMU's declared range)"),
    (("crusher", "parameters"), {"gap": 0.25}, "crusher.parameters.gap", "'gap_width'"),
])
def test_bad_values_name_the_key_and_the_allowed_range(path, value, field, allowed):
    with pytest.raises(ValidationError) as error:
        validate(_broken(path, value))
    assert error.value.field == field
    assert allowed in str(error.value)


def test_truck_routes_must_name_sources():
    config = copy.deepcopy(load(EXAMPLE))
    config["trucks"][0]["route"] = ["left", "middle"]
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
    assert "sources.left.grade: must be finite and >= 0 and <= 1" in result.stderr
    result = _minetwin("simulate", str(EXAMPLE), "--out", str(tmp_path / "out"),
                       "--storage-model", "magic")
    assert result.returncode == 2 and "--storage-model: must be one of" in result.stderr
    assert _minetwin("simulate", "--help").returncode == 0
    assert _minetwin("reproduce", "--help").returncode == 0
