"""The demo's integration-test verdict: one line of the audit, and the warnings the
test's own log would hide (the demo runs it with its stderr in a file)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "monitor_demo.py"


def _monitor_demo():
    spec = importlib.util.spec_from_file_location("monitor_demo", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


REPORT = {"tracking_ids_lost": 0, "tracking_ids_duplicated": 0, "mass_balance_rel_error": 0.0,
          "lag_p99_s": 0.06, "step_time_p99_ms": 41.0, "keeps_up": True, "max_lag_s": 0.4,
          "out_of_training_range_at_end": []}


def test_a_run_that_kept_real_time_prints_one_line_and_no_warning(capsys):
    _monitor_demo().print_verdict(REPORT)
    out, err = capsys.readouterr()
    assert out.strip() == ("integration-test: 0 ids lost, 0 duplicated, mass balance 0.0e+00, "
                           "lag p99 0.06 s, step p99 41 ms, kept real time: yes")
    assert err == ""


def test_a_run_that_fell_behind_says_so_and_names_the_input_out_of_range(capsys):
    report = dict(REPORT, keeps_up=False, max_lag_s=15.8, lag_p99_s=7.59,
                  out_of_training_range_at_end=["mass_distribution_residual"])
    _monitor_demo().print_verdict(report)
    out, err = capsys.readouterr()
    assert out.strip().endswith("kept real time: NO")
    assert "lagged up to 15.8 s" in err
    assert "outside its training range in mass_distribution_residual" in err
