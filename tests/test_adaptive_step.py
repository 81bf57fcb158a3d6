"""The communication step adapted during a run (``cosim.master.AdaptiveStep``,
``simulation.communication_step = "adaptive"``) on the paper's step-response mine."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cosim.analyses.coupling_step import errors_against
from cosim.scenario import load, run_scenario
from minetwin.cli import main

SCENARIO = Path(__file__).resolve().parents[1] / "examples" / "step_response.toml"
SIGNALS = ["crusher_fmu.power", "mill_fmu.power"]
TOLERANCE = 0.15
UNTIL = 1200.0


def _run(**simulation):
    config = load(SCENARIO)
    # one recording interval for every run (the largest adaptive step): window means alike
    config["simulation"].update(record_every_s=2.0, coupling_signals=SIGNALS,
                                coupling_tolerance=TOLERANCE, **simulation)
    simulation_, summary = run_scenario(config, until=UNTIL)
    try:
        return simulation_.timeseries, summary, list(simulation_.master.step_changes)
    finally:
        simulation_.close()


ADAPTIVE = {"step_s": 0.5, "communication_step": "adaptive", "step_min_s": 0.125,
            "step_max_s": 2.0}


def test_adaptive_step_stays_within_the_tolerance_with_fewer_steps_than_0_5_s():
    """1200 s of the step-response mine: the adaptive run's window means (60 s) of the
    crusher and mill power are within the tolerance of a 0.125 s fixed-step run's, it
    takes fewer communication steps than the fixed 0.5 s run, uses both smaller and
    larger steps than 0.5 s, logs every change, and the same seed gives the same run."""
    reference, _, _ = _run(step_s=0.125)
    fixed, fixed_summary, _ = _run(step_s=0.5)
    adaptive, summary, changes = _run(**ADAPTIVE)
    errors = errors_against(reference, adaptive, SIGNALS, window_s=60.0, until=UNTIL)
    assert all(error <= TOLERANCE for error in errors.values()), errors
    steps = summary["communication_steps"]
    assert steps["mode"] == "adaptive" and steps["tolerance"] == TOLERANCE
    assert steps["count"] < fixed_summary["communication_steps"]["count"] == 2400
    assert steps["min_s"] < 0.5 < steps["max_s"] <= 2.0 and steps["min_s"] >= 0.125
    assert steps["mean_s"] == pytest.approx(UNTIL / steps["count"])
    assert steps["changes"] == len(changes) > 0
    assert all(c["from_s"] != c["to_s"] and c["signal"] in SIGNALS for c in changes)
    assert summary["simulated_s"] == UNTIL
    np.testing.assert_allclose(adaptive.index.to_numpy(), np.arange(1, 601) * 2.0)
    again, again_summary, again_changes = _run(**ADAPTIVE)
    pd.testing.assert_frame_equal(adaptive, again)
    assert again_changes == changes and again_summary["communication_steps"] == steps


@pytest.mark.parametrize("settings, field", [
    ({"communication_step": "sometimes"}, "communication_step"),
    ({"communication_step": "adaptive", "coupling_signals": []}, "coupling_signals"),
    ({"communication_step": "adaptive", "coupling_tolerance": None}, "coupling_tolerance"),
    ({"communication_step": "adaptive", "step_max_s": 3.0}, "step_max_s"),
    ({"communication_step": "adaptive", "step_min_s": 0.2}, "step_min_s"),
    ({"communication_step": "adaptive", "step_min_s": 1.0}, "step_min_s"),
    ({"communication_step": "adaptive", "record_every_s": 1.0}, "record_every_s"),
])
def test_bad_adaptive_settings_are_refused_naming_the_field(tmp_path, capsys, settings, field):
    text = SCENARIO.read_text().replace(
        "[simulation]\n",
        "[simulation]\ncoupling_signals = [\"crusher_fmu.power\"]\ncoupling_tolerance = 0.1\n"
        "step_max_s = 2.0\n", 1).replace("record_every_s = 1.0", "record_every_s = 2.0", 1)
    for key, value in settings.items():
        lines = [line for line in text.splitlines() if not line.startswith(f"{key} =")]
        text = "\n".join(lines) + "\n"
        if value is not None:
            literal = ("[" + ", ".join(f'"{v}"' for v in value) + "]" if isinstance(value, list)
                       else f'"{value}"' if isinstance(value, str) else repr(value))
            text = text.replace("[simulation]\n", f"[simulation]\n{key} = {literal}\n", 1)
    path = tmp_path / "scenario.toml"
    path.write_text(text)
    assert main(["simulate", str(path), "--until", "10", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"simulation.{field}" in err and "Traceback" not in err


def test_coupling_step_adaptive_needs_the_fixed_0_5_s_step_in_its_ladder(tmp_path, capsys):
    code = main(["coupling-step", str(SCENARIO), "--steps", "1,2", "--adaptive",
                 "--signals", "crusher_fmu.power", "--tolerance", "0.1", "--until", "60",
                 "--out", str(tmp_path / "x")])
    assert code == 2
    assert "--steps" in capsys.readouterr().err
