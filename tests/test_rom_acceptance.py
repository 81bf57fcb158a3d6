"""``minetwin rom evaluate --mine S --integration-test S``: the paper-scale mine with the
evaluated ROM as its stockpile and the paper's integration test over OPC UA, run for
real (the mine's FMUs through fmpy, the mock 800xA server, the ROM stockpile client and
the monitor as processes on 127.0.0.1), carried in summary.json beside the held-out
scores. Speeds are recorded, never asserted: the targets' flags must agree with the
figures they are computed from."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from minetwin.acceptance import MASS_BALANCE_LIMIT, MINE_REALTIME_TARGET
from surrogate.rom.storage import DEFAULT_MODEL

ROOT = Path(__file__).resolve().parents[1]
HELDOUT = ROOT / "surrogate" / "rom" / "data" / "paper_heldout"


def _evaluate(out, *extra):
    return subprocess.run(
        [sys.executable, "-m", "minetwin.cli", "rom", "evaluate", "--model", str(DEFAULT_MODEL),
         "--data", str(HELDOUT), "--out", str(out), "--workers", "1", *extra],
        cwd=ROOT, capture_output=True, text=True)


@pytest.mark.slow
def test_the_summary_carries_the_mine_and_the_integration_test(tmp_path):
    result = _evaluate(tmp_path, "--mine", "30", "--integration-test", "10")
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text(),
                         parse_constant=lambda name: pytest.fail(f"{name} in summary.json"))
    mine = summary["mine"]
    assert mine["scenario"] == "examples/paper_scale.toml" and mine["simulated_s"] == 30.0
    assert mine["realtime_factor_cpu"] == pytest.approx(30.0 / mine["cpu_s"])
    assert mine["mass_balance_rel_error"] < 1e-9
    assert mine["particles_created"] > 15000  # the 1.9 kt pile, pseudo-particles of 12-160 kg
    assert summary["targets"]["mine_realtime_factor_at_least_100"] == (
        mine["realtime_factor_cpu"] >= MINE_REALTIME_TARGET)
    run = summary["integration_test"]
    assert run["stockpile_model"] == "rom" and run["speed"] == 1.0
    assert run["duration_s"] == pytest.approx(10.0)
    assert run["tracking_ids_lost"] == 0 and run["tracking_ids_duplicated"] == 0
    assert run["mass_balance_rel_error"] < MASS_BALANCE_LIMIT
    assert run["exchange_cycles"] > 0 and run["exchange_cycle_s"] == 0.1
    assert isinstance(run["out_of_training_range_at_end"], list)
    assert run["report"] == "integration_test/report.json"
    assert (tmp_path / run["report"]).is_file()
    in_real_time = (run["step_time_p99_ms"] / 1e3 < run["exchange_cycle_s"]
                    and run["lag_p99_s"] < run["exchange_cycle_s"])
    assert summary["targets"]["integration_test_real_time_without_loss"] == in_real_time


@pytest.mark.parametrize("extra, named", [
    (["--mine", "0"], "--mine"),
    (["--mine", "nan"], "--mine"),
    (["--integration-test", "-5"], "--integration-test"),
    (["--integration-test", "1e9"], "--integration-test"),
])
def test_a_bad_duration_is_refused_by_name_before_anything_runs(tmp_path, extra, named):
    result = _evaluate(tmp_path, *extra)
    assert result.returncode == 2 and named in result.stderr, result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "summary.json").exists()


def test_the_checks_are_refused_with_a_quick_design(tmp_path):
    result = subprocess.run([sys.executable, "-m", "minetwin.cli", "rom", "evaluate", "--quick",
                             "--out", str(tmp_path), "--mine"],
                            cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 2 and "--mine" in result.stderr, result.stderr
    assert not any(tmp_path.iterdir())  # refused before a design is built


def test_a_check_that_cannot_run_is_recorded_and_the_scores_are_kept(tmp_path):
    """A held-out evaluation takes minutes: a mine or integration test that fails
    afterwards is recorded as its error, with its target not met, rather than raised."""
    from minetwin.acceptance import run_from_command_line

    summary = {"tracking_error": {"rom": 0.1}, "targets": {"speedup_at_least_100": True}}
    missing = tmp_path / "no_model.npz"
    errors = run_from_command_line(summary, missing, tmp_path, mine_until=10.0,
                                   integration_duration=5.0, rom_options={})
    assert [e.split(":")[0] for e in errors] == ["mine", "integration test"]
    assert str(missing) in summary["mine"]["error"]
    assert "integration-test exited 2" in summary["integration_test"]["error"]
    assert summary["targets"] == {"speedup_at_least_100": True,
                                  "mine_realtime_factor_at_least_100": False,
                                  "integration_test_real_time_without_loss": False}
    assert summary["tracking_error"] == {"rom": 0.1}
