"""The demo's integration-test verdict: one line of the audit, and the warnings the
test printed at its end, which its log would hide (the demo runs it with its stderr
in a file)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from minetwin.commands.integration import WARNING_PREFIX, end_warnings

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "monitor_demo.py"


def _monitor_demo():
    spec = importlib.util.spec_from_file_location("monitor_demo", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


REPORT = {"tracking_ids_lost": 0, "tracking_ids_duplicated": 0, "mass_balance_rel_error": 0.0,
          "lag_p99_s": 0.06, "step_time_p99_ms": 41.0, "keeps_up": True, "max_lag_s": 0.4,
          "out_of_training_range_at_end": []}


LOG = ("integration-test: server opc.tcp://127.0.0.1:4840\n"
       "integration-test: stockpile REST http://127.0.0.1:8000\n")


def test_a_run_that_kept_real_time_prints_one_line_and_no_warning(capsys):
    assert end_warnings(REPORT, 2.0) == []
    _monitor_demo().print_verdict(REPORT, LOG)
    out, err = capsys.readouterr()
    assert out.strip() == ("integration-test: 0 ids lost, 0 duplicated, mass balance 0.0e+00, "
                           "lag p99 0.06 s, step p99 41 ms, kept real time: yes")
    assert err == ""


def test_a_run_that_fell_behind_says_so_and_names_the_input_out_of_range(capsys):
    report = dict(REPORT, keeps_up=False, max_lag_s=15.8, lag_p99_s=7.59,
                  out_of_training_range_at_end=["mass_distribution_residual"])
    warnings = end_warnings(report, 2.0)
    assert len(warnings) == 2
    assert "lagged up to 15.8 s" in warnings[0] and "more than 2 s" in warnings[0]
    assert "outside its training range in mass_distribution_residual" in warnings[1]
    log = LOG + "".join(f"{WARNING_PREFIX}{w}\n" for w in warnings)
    _monitor_demo().print_verdict(report, log)
    out, err = capsys.readouterr()
    assert out.strip().endswith("kept real time: NO")
    assert err.splitlines() == [f"{WARNING_PREFIX}{w}" for w in warnings]
