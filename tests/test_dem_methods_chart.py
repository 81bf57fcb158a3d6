"""examples/dem_methods_chart.py: the error-against-cost study of both DEM methods.

The quick variant runs in-process (its runs on 2 worker processes). Checked
are the structure and exact invariants of the table, not the value of any one
chaotic run: every planned run is there once, the reference holds, a
nonsmooth run never uses more sweeps than allowed, a failure names a known
kind with a time inside the run and a picture, a run stopped by a failure
has no error values, the JSON is strict, and the figures follow
``cosim.plotstyle``.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

from cosim import plotstyle
from surrogate.dem import DemConfig
from surrogate.dem import method_study as study

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "examples" / "dem_methods_chart.py"


def _load():
    spec = importlib.util.spec_from_file_location("dem_methods_chart", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _strict(text: str):
    def refuse(name):
        raise ValueError(f"non-strict JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


@pytest.mark.slow
def test_the_quick_study_writes_a_complete_strict_table_and_styled_charts(tmp_path):
    seen = {}

    def hook(fig, path):
        seen[Path(path).name] = plotstyle.problems(fig)

    plotstyle.SAVE_HOOKS.append(hook)
    try:
        assert _load().main(["--quick", "--out", str(tmp_path), "--workers", "2"]) == 0
    finally:
        plotstyle.SAVE_HOOKS.remove(hook)
    size = study.QUICK
    result = _strict((tmp_path / "dem_methods.json").read_text())
    runs = result["runs"]
    per_group = 2 + len(size.explicit_factors) + len(size.nonsmooth_steps) * len(
        size.nonsmooth_iterations) * len(size.nonsmooth_relaxations)
    assert size.nonsmooth_relaxations == (1.0, study.OVER_RELAXATION)
    groups = {(r["scene"], r["stiffness"]) for r in runs}
    assert groups == {(s, k) for s in ("settled", "funnel", "inflow") for k in ("soft", "rock")}
    assert len(runs) == 6 * per_group
    keys = {(r["scene"], r["stiffness"], r["method"], r["dt_s"], r["iterations"],
             r["relaxation"], r["replica"]) for r in runs}
    assert len(keys) == len(runs)  # every planned run once
    durations = {"settled": size.settled_s, "funnel": size.funnel_s,
                 "inflow": size.inflow_total_s}
    for r in runs:
        assert r["normal_stiffness_N_m"] == study.STIFFNESSES[r["stiffness"]]
        if r["method"] == "nonsmooth":
            assert r["iterations"] in size.nonsmooth_iterations
            assert r["relaxation"] in size.nonsmooth_relaxations
            # a step solved again for missed contacts sweeps again
            resolves = DemConfig().missed_contact_resolves
            assert 0.0 < r["mean_sweeps_per_step"] <= r["iterations"] * (1 + resolves)
            assert any(abs(r["dt_s"] - dt) < 1e-15 for dt in size.nonsmooth_steps)
        else:
            assert r["iterations"] is None and r["relaxation"] is None
            assert any(abs(r["dt_over_stable"] - f) < 1e-9
                       for f in (study.REFERENCE_FACTOR, *size.explicit_factors))
        if r["reference"]:
            assert r["method"] == "explicit" and r["replica"] == 0
            assert abs(r["dt_over_stable"] - study.REFERENCE_FACTOR) < 1e-9
            assert r["failure"] is None
            assert r["simulated_s"] == pytest.approx(durations[r["scene"]], abs=r["dt_s"])
            if r["scene"] == "funnel":
                assert r["discharge_rate_kg_s"] > 0
                assert r["tracking_error"] == 0.0 and r["discharge_rate_error"] == 0.0
        failure = r["failure"]
        if failure is None:
            assert r["simulated_s"] == pytest.approx(durations[r["scene"]], abs=r["dt_s"])
            assert r["wall_s_per_simulated_s"] > 0
            continue
        assert failure["kind"] in study.FAILURE_CRITERIA
        assert 0.0 < failure["time_s"] <= durations[r["scene"]] + r["dt_s"]
        assert failure["reason"]
        assert Path(failure["picture"]).is_file()
        assert Path(failure["picture"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        if failure["kind"] in ("blow-up", "leaked"):
            assert r["angle_error_deg"] is None and r["tracking_error"] is None
        if failure["kind"] in ("compressed", "jammed", "leaked"):
            assert r["method"] == "nonsmooth"
    for r in runs:  # the noise floor is the replica's error, the same for its whole group
        replica = next(x for x in runs if x["scene"] == r["scene"]
                       and x["stiffness"] == r["stiffness"] and x["replica"] == 1)
        floor = {k: replica[k] for k in ("angle_error_deg", "discharge_rate_error",
                                         "penetration_ratio_to_reference", "tracking_error")}
        assert r["noise_floor"] == floor
    with open(tmp_path / "dem_methods.csv", newline="") as handle:
        lines = list(csv.reader(handle))
    assert len(lines) == len(runs) + 1
    assert all(len(line) == len(lines[0]) for line in lines)
    for name in ("dem_methods_soft.png", "dem_methods_rock.png"):
        assert (tmp_path / name).is_file()
        assert seen[name] == []
    for name, problems in seen.items():  # the failure pictures too
        assert problems == [], name


def test_bad_workers_are_refused_with_exit_2_and_no_traceback(tmp_path):
    proc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path),
                           "--workers", "0"], capture_output=True, text=True, cwd=ROOT,
                          timeout=120)
    assert proc.returncode == 2
    assert "--workers" in proc.stderr and ">= 1" in proc.stderr
    assert "Traceback" not in proc.stderr


def _row(method, **fields):
    row = {"scene": "funnel", "stiffness": "soft", "method": method, "dt_s": 1e-5,
           "dt_over_stable": 0.25 if method == "explicit" else None, "iterations": None,
           "replica": 0, "simulated_s": 1.0, "mean_penetration": 1e-4,
           "max_penetration": 1e-3, "angle_of_repose_deg": None, "discharge_rate_kg_s": 100.0,
           "beverloo_kg_s": 120.0, "failure": None,
           "outflow": {"time": [0.1, 0.6], "tracking_id": [0, 1], "mass": [50.0, 50.0]}}
    row.update(fields)
    return row


def test_a_run_stopped_during_the_run_has_no_errors_and_keeps_its_failure():
    stopped = {"kind": "compressed", "what": "overlap", "time_s": 0.3, "reason": "guard"}
    rows = [_row("explicit"), _row("explicit", replica=1),
            _row("nonsmooth", dt_s=0.011, dt_over_stable=None, iterations=10,
                 discharge_rate_kg_s=None, beverloo_kg_s=None, failure=stopped,
                 outflow={"time": [], "tracking_id": [], "mass": []})]
    table = study.evaluate(rows, study.QUICK)
    run = next(r for r in table if r["method"] == "nonsmooth")
    assert run["failure"] == stopped
    assert run["discharge_rate_error"] is None and run["tracking_error"] is None
    reference = next(r for r in table if r["reference"])
    assert reference["discharge_rate_error"] == 0.0 and reference["tracking_error"] == 0.0
