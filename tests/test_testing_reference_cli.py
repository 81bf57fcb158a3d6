"""``minetwin reference record|compare`` on the example plant (in-process: the runs are short)."""

import shutil
from pathlib import Path

import pandas as pd
import pytest

from minetwin.cli import main

PLANT = Path(__file__).resolve().parent.parent / "examples" / "cosim_tests" / "plant.toml"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    folder = tmp_path_factory.mktemp("reference")
    scenario = folder / "plant.toml"
    shutil.copy(PLANT, scenario)
    reference = folder / "plant_reference.csv"
    assert main(["reference", "record", str(scenario), "--out", str(reference),
                 "--until", "150"]) == 0
    return scenario, reference


def test_record_writes_the_signals_the_scenario_names(recorded):
    _, reference = recorded
    frame = pd.read_csv(reference)
    assert list(frame.columns) == ["time", "crusher_fmu.power", "crusher.zone_hardness_avg",
                                   "stockpile.d_mean", "mill_fmu.power", "mill.d_mean"]
    assert frame["time"].iloc[-1] == 150.0 and frame["crusher_fmu.power"].max() > 1000.0


def test_compare_passes_a_rerun_and_fails_a_changed_signal_with_table_and_overlay(
        recorded, tmp_path, capsys):
    scenario, reference = recorded
    assert main(["reference", "compare", str(scenario), str(reference)]) == 0
    out = capsys.readouterr().out
    assert "all signals inside their bands" in out and "FAIL" not in out

    frame = pd.read_csv(reference)
    frame["mill_fmu.power"] *= 1.03                        # the mill drew 3 % less before
    changed = tmp_path / "changed.csv"
    frame.to_csv(changed, index=False, float_format="%.17g")
    assert main(["reference", "compare", str(scenario), str(changed), "--out",
                 str(tmp_path / "compare")]) == 1
    plots = tmp_path / "compare" / "overlays"
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    row = next(line for line in lines if line.startswith("mill_fmu.power"))
    assert row.split()[-1] == "FAIL"
    # the table gives each signal's unit; the overlays go under --out, none beside the CSV
    header = next(line for line in lines if line.startswith("signal"))
    assert header.split()[:2] == ["signal", "unit"] and row.split()[1] == "W"
    assert not list(changed.parent.glob("*.png")) and not (changed.parent / "overlays").exists()
    assert next(line for line in lines if line.startswith("crusher_fmu.power")).endswith("pass")
    assert "1 of 5 signal(s) outside their band" in captured.out
    assert "signal 'mill_fmu.power' leaves its tolerance band" in captured.err
    assert [p.name for p in plots.glob("*.png")] == ["mill_fmu.power.png"]


def test_bad_input_exits_2_naming_the_field(recorded, tmp_path, capsys):
    scenario, reference = recorded
    assert main(["reference", "compare", str(scenario), str(tmp_path / "none.csv")]) == 2
    assert "reference: must be an existing reference CSV" in capsys.readouterr().err
    assert main(["reference", "compare", str(scenario), str(reference), "--set",
                 "assets.crusher.nonsense=1"]) == 2
    assert "assets.crusher.nonsense: must be one of" in capsys.readouterr().err
    bare = tmp_path / "bare.toml"
    bare.write_text(PLANT.read_text().split("[reference]")[0])
    assert main(["reference", "record", str(bare), "--out", str(tmp_path / "x.csv")]) == 2
    assert "reference: must be a [reference] table naming the signals" in capsys.readouterr().err


def test_a_run_that_fails_exits_1_with_the_simulator_message(recorded, capsys):
    scenario, reference = recorded
    assert main(["reference", "compare", str(scenario), str(reference), "--set",
                 "assets.left.length_m=3"]) == 1      # the left ore body runs out
    err = capsys.readouterr().err
    assert "minetwin reference compare: the run of" in err and "ore body exhausted" in err


def test_a_reference_recorded_on_another_cpu_passes_here(recorded, tmp_path):
    """Recorded with another BLAS kernel, numba target and libm (as on another machine;
    see tests/test_reproducibility.py), compared here with the default bands."""
    import os
    import subprocess
    import sys

    from cosim.numerics import ANOTHER_CPU_ENV

    scenario, _ = recorded
    elsewhere = tmp_path / "recorded_elsewhere.csv"
    subprocess.run([sys.executable, "-m", "minetwin.cli", "reference", "record", str(scenario),
                    "--out", str(elsewhere), "--until", "150"], check=True,
                   capture_output=True, env={**os.environ, **ANOTHER_CPU_ENV})
    assert main(["reference", "compare", str(scenario), str(elsewhere)]) == 0
