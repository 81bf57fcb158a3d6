"""The largest communication step within a coupling tolerance, by step doubling
(``cosim.analyses.coupling_step``, ``minetwin coupling-step``)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from cosim.analyses.coupling_step import coupling_errors, largest_step_within, window_means
from cosim.errors import ValidationError
from minetwin.cli import main

PLANT = "examples/cosim_tests/plant.toml"


def _first_order_runs(steps, c=0.2):
    """y_H(t) = 1 + sin(t / 50) + c H: a signal whose coupling error is exactly c H."""
    t = np.arange(1.0, 601.0, 1.0)
    return {h: pd.DataFrame({"a.y": 1.0 + np.sin(t / 50.0) + c * h},
                            index=pd.Index(t, name="time")) for h in steps}


def test_step_doubling_recovers_a_first_order_error_exactly():
    steps = [0.125, 0.25, 0.5, 1.0, 2.0]
    runs = _first_order_runs(steps)
    table = coupling_errors(runs, ["a.y"], window_s=60.0, until=600.0)
    scale = np.nanmax(np.abs(window_means(runs[0.125], "a.y", 60.0, 600.0)))
    for h in steps[1:]:
        row = table[h]["a.y"]
        assert row["estimate"] == pytest.approx(0.2 * h / scale, rel=1e-9)
        assert row["against_finest"] == pytest.approx(0.2 * (h - 0.125) / scale, rel=1e-9)
    assert table[1.0]["a.y"]["order"] == pytest.approx(1.0, rel=1e-9)
    assert table[0.125]["a.y"]["estimate"] is None
    # the estimate is 0.2 H / scale: within 0.1 up to H = 0.5 * scale, doubled steps only
    tolerance = 0.2 * 0.5 / scale * 1.01
    assert largest_step_within(table, tolerance) == 0.5
    assert largest_step_within(table, 0.2 * 0.25 / scale * 0.5) is None


def test_a_ladder_that_is_not_doublings_or_an_unrecorded_signal_is_refused():
    with pytest.raises(ValidationError, match="ladder of doublings"):
        coupling_errors(_first_order_runs([0.25, 0.75]), ["a.y"], window_s=60.0, until=600.0)
    with pytest.raises(ValidationError, match="'b.y' is not recorded"):
        coupling_errors(_first_order_runs([0.25, 0.5]), ["b.y"], window_s=60.0, until=600.0)
    with pytest.raises(ValidationError, match="coupling_tolerance"):
        largest_step_within({}, 0.0)


def test_the_chosen_step_is_within_the_tolerance_against_a_fine_step_run(tmp_path, capsys):
    """The test plant (300 s) at 0.125-1 s: the chosen step's window means of the
    crusher and mill power stay within the tolerance of the finest run's, and
    every larger step's estimate exceeds it."""
    out = tmp_path / "coupling"
    code = main(["coupling-step", PLANT, "--steps", "0.125,0.25,0.5,1", "--until", "300",
                 "--signals", "crusher_fmu.power,mill_fmu.power", "--tolerance", "0.15",
                 "--window", "60", "--workers", "2", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    result = json.loads((out / "coupling_step.json").read_text())
    chosen = result["chosen_step_s"]
    assert chosen in (0.25, 0.5, 1.0)
    rows = {row["step_s"]: row for row in result["steps"]}
    for signal, row in rows[chosen]["signals"].items():
        assert row["estimate"] <= 0.15 and row["against_finest"] <= 0.15, signal
    larger = [h for h in rows if h > chosen]
    if larger:
        assert any(r["estimate"] > 0.15 for r in rows[min(larger)]["signals"].values())
    assert all(row["wall_s_per_s"] > 0 for row in rows.values())
    assert (out / "coupling_step.png").stat().st_size > 0
    assert f"chosen step {chosen:g} s" in capsys.readouterr().out


def test_bad_input_names_the_field(tmp_path, capsys):
    base = ["coupling-step", PLANT, "--until", "60", "--out", str(tmp_path / "x")]
    assert main(base + ["--signals", "crusher_fmu.power", "--tolerance", "0.1",
                        "--steps", "0.5,fast"]) == 2
    assert "--steps" in capsys.readouterr().err
    assert main(base + ["--signals", "crusher_fmu.power", "--tolerance", "0.1",
                        "--steps", "0.25,0.75"]) == 2      # refused before anything runs
    assert "--steps: must be a ladder of doublings" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    assert main(base + ["--tolerance", "0.1"]) == 2       # the plant declares no signals
    assert "--signals" in capsys.readouterr().err
    assert main(base + ["--signals", "crusher_fmu.power", "--tolerance", "1.5"]) == 2
    assert "--tolerance: must be in (0, 1]" in capsys.readouterr().err
