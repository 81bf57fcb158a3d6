"""``minetwin simulate --rest-port`` serves the simulated stockpile to the monitor."""

import json
import re
import subprocess
import sys
import time
import urllib.request

import pytest

from cosim.fmu import fmu_path


def _get(url):
    with urllib.request.urlopen(url, timeout=5) as response:
        return json.load(response)


def test_simulate_serves_its_stockpile_over_rest_while_running(tmp_path):
    if not fmu_path("crusher").exists():
        pytest.skip("FMUs not built: run `minetwin fmus build` (make test does)")
    process = subprocess.Popen(
        [sys.executable, "-m", "minetwin.cli", "simulate", "examples/step_response.toml",
         "--until", "120", "--out", str(tmp_path / "run"), "--rest-port", "0",
         "--realtime-factor", "15", "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = None
        deadline = time.monotonic() + 60
        while url is None and time.monotonic() < deadline:
            line = process.stderr.readline()
            match = re.search(r"stockpile REST on (http://127\.0\.0\.1:\d+)", line)
            if match:
                url = match.group(1)
        assert url, "simulate did not announce its REST address"
        assert _get(url + "/health")["status"] == "ok"
        first = _get(url + "/totals")
        time.sleep(2.0)
        second = _get(url + "/totals")
        assert second["time_s"] > first["time_s"], "simulation time did not advance"
        assert second["held_mass_kg"] >= 0
        # origin is the index of the source a particle was mined at, named after it
        table = {"total": 0}
        while not table["total"] and time.monotonic() < deadline + 30:
            table = _get(url + "/particles?limit=50000")
            time.sleep(0.5)
        names = {o["origin"]: o["name"] for o in table["origin_names"]}
        assert table["total"] and set(table["origin"]) == set(names)
        assert set(names.values()) <= {"source left", "source right"}
        stdout, _ = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["simulated_s"] == 120
    assert summary["mass_balance_rel_error"] < 1e-9


def test_realtime_factor_needs_a_rest_port(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "minetwin.cli", "simulate", "examples/step_response.toml",
         "--until", "1", "--out", str(tmp_path), "--realtime-factor", "2"],
        capture_output=True, text=True)
    assert result.returncode == 2
    assert "--realtime-factor: must be given together with --rest-port" in result.stderr
