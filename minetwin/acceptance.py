"""The paper-scale checks beside the held-out scenes that ``minetwin rom evaluate``
adds to its summary.json (``--mine``, ``--integration-test S``).

- ``mine_speed``: the paper's mine simulator (``examples/paper_scale.toml``: two
  sources, the haul truck, crusher and mill FMUs, two belts, a 1.9 kt stockpile
  of about 19,000 pseudo-particles) with the evaluated ROM as its stockpile,
  timed as ``benchmarks/bench_mine.py`` times it (5 s untimed first, so the
  kernels compile outside the timing; events recorded to SQLite). Target: at
  least ``MINE_REALTIME_TARGET`` x real time on one core, by the process's CPU
  time (the fairer figure on a shared machine; wall time is reported beside it).
- ``integration_test``: the paper's integration test (``minetwin
  integration-test``: mock 800xA server, the ROM stockpile as its OPC UA client,
  the monitor) at speed 1 with the evaluated ROM. Targets: step-time p99 and lag
  p99 each below the exchange cycle, no tracking id lost or duplicated, mass
  balance below ``MASS_BALANCE_LIMIT``; the report names any ROM input outside
  its training ranges at the end.
"""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
import time
import warnings
from pathlib import Path

from cosim.errors import ValidationError

ROOT = Path(__file__).resolve().parents[1]

MINE_SCENARIO = ROOT / "examples" / "paper_scale.toml"
"""The paper's mine at full scale."""

MINE_REALTIME_TARGET = 100.0
"""Simulated seconds per CPU second the mine must reach with the ROM stockpile."""

MASS_BALANCE_LIMIT = 1e-9
"""Largest relative mass-balance error of the integration test."""

MINE_UNTIL_MAX_S = 1e6
"""Longest mine run [s of simulation] ``mine_speed`` takes."""

INTEGRATION_TEST_MAX_S = 86400.0
"""Longest integration test [s] ``integration_test`` takes (the command's own limit)."""


def check_duration(field: str, seconds, limit: float) -> float:
    """``seconds`` as a float if it lies in (0, ``limit``] s, else a ValidationError
    naming ``field``."""
    if not 0 < seconds <= limit:
        raise ValidationError(field, f"in (0, {limit:g}] s", f"got {seconds!r}")
    return float(seconds)


def mine_config(model_file, rom_options: dict | None = None) -> dict:
    """The paper-scale mine's scenario with the ROM in ``model_file`` (and
    ``rom_options``, ``RomStorage`` keywords) as its stockpile; refuses a scenario
    that cannot run here (e.g. FMUs not built) with the scenario's own error."""
    from cosim.scenario import load

    config = load(MINE_SCENARIO)
    stockpile = config["assets"]["stockpile"]
    stockpile["model"] = "rom"
    stockpile["options"] = {**stockpile.get("options", {}), **(rom_options or {}),
                            "model": str(model_file)}
    return config


def timed_scenario(config: dict, out, until: float, *, storage_model: str | None = None,
                   progress: bool | str = False):
    """Run ``config`` into ``out`` for ``until`` [s] as ``cosim.scenario.run_scenario``
    does (events to SQLite), timed; returns ``(simulation, summary, timing)`` with
    timing's ``wall_s``, ``cpu_s`` (this process's CPU time), ``warnings`` (each
    distinct one raised, as text) and ``stockpile_particles_end``."""
    from cosim.scenario import run_scenario

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        started, cpu_started = time.perf_counter(), time.process_time()
        simulation, summary = run_scenario(config, out, until=until,
                                           storage_model=storage_model, progress=progress)
        wall = time.perf_counter() - started
        cpu = time.process_time() - cpu_started
    held = simulation.plant.particles.owner == simulation.assets["stockpile"].owner
    return simulation, summary, {
        "wall_s": wall, "cpu_s": cpu,
        "warnings": sorted({f"{w.category.__name__}: {w.message}" for w in caught}),
        "stockpile_particles_end": int(held.sum())}


def mine_speed(model_file, *, until: float = 7200.0, rom_options: dict | None = None) -> dict:
    """Run the paper-scale mine (``mine_config``) for ``until`` [s] (default 7,200);
    the real-time factors, particles, mass balance, the ROM's warnings and whether
    the target is met."""
    from cosim.scenario import run_scenario

    until = check_duration("mine_until", until, MINE_UNTIL_MAX_S)
    config = mine_config(model_file, rom_options)
    with tempfile.TemporaryDirectory() as out:
        with warnings.catch_warnings():  # the untimed run's warnings are the timed run's
            warnings.simplefilter("ignore")
            run_scenario(config, out, until=5.0)
        load_average = os.getloadavg()[0]
        _, summary, timing = timed_scenario(config, out, until, progress="mine")
    factor_cpu = until / timing["cpu_s"]
    return {"scenario": str(MINE_SCENARIO.relative_to(ROOT)), "simulated_s": until,
            "wall_s": timing["wall_s"], "cpu_s": timing["cpu_s"],
            "realtime_factor": until / timing["wall_s"],
            "realtime_factor_cpu": factor_cpu, "load_average_at_start": load_average,
            "particles_created": summary["particles_created"],
            "stockpile_particles_end": timing["stockpile_particles_end"],
            "mass_balance_rel_error": summary["mass_balance_rel_error"],
            "warnings": timing["warnings"],
            "target_realtime_factor_cpu": MINE_REALTIME_TARGET,
            "realtime_factor_at_least_100": bool(factor_cpu >= MINE_REALTIME_TARGET)}


def integration_test(model_file, out, *, duration: float = 60.0,
                     rom_options: dict | None = None) -> dict:
    """Run ``minetwin integration-test`` at speed 1 for ``duration`` [s] (default 60)
    with the ROM in ``model_file`` into ``out`` (its report: ``out``/report.json);
    the report's key figures and whether it ran in real time without loss."""
    from minetwin.harness import minetwin_command

    duration = check_duration("integration_test", duration, INTEGRATION_TEST_MAX_S)
    out = Path(out)
    options = {**(rom_options or {}), "model": str(model_file)}
    command = minetwin_command() + ["integration-test", "--duration", repr(duration),
                                    "--speed", "1", "--out", str(out)]
    for key, value in options.items():
        command += ["--option", f"{key}={value}"]
    # its progress goes to this process's stderr; its report is read from the file
    finished = subprocess.run(command, stdout=subprocess.DEVNULL, cwd=ROOT)
    report_path = out / "report.json"
    if not report_path.exists():
        raise ValidationError("integration_test", "a run that writes its report",
                              f"minetwin integration-test exited {finished.returncode} "
                              f"without {report_path}; see its logs in {out}")
    report = json.loads(report_path.read_text())
    cycle = report["exchange_cycle_s"]
    keys = ("duration_s", "speed", "stockpile_model", "tracking_ids_lost",
            "tracking_ids_duplicated", "mass_balance_rel_error", "lag_p99_s", "max_lag_s",
            "step_time_p99_ms", "step_time_mean_ms", "exchange_cycles", "exchange_cycle_s",
            "out_of_training_range_at_end", "monitor_ok")
    result = {key: report[key] for key in keys}
    result["real_time_without_loss"] = bool(
        report["step_time_p99_ms"] / 1e3 < cycle and report["lag_p99_s"] < cycle
        and report["tracking_ids_lost"] == 0 and report["tracking_ids_duplicated"] == 0
        and report["mass_balance_rel_error"] < MASS_BALANCE_LIMIT)
    return result


def run_from_command_line(summary: dict, model_file, out, *, mine_until: float | None,
                          integration_duration: float | None, rom_options: dict,
                          progress=None) -> list[str]:
    """Add the checks asked for to ``summary`` (``mine``, ``integration_test`` and
    their ``targets``), in place; the integration test writes its report and logs
    into ``out``/integration_test. A check that cannot run is recorded as its
    ``error`` (its target not met), so the held-out scores already computed are
    kept; returns those errors."""
    say = progress or (lambda message: None)
    errors = []
    if mine_until is not None:
        say(f"paper-scale mine with this ROM for {mine_until:.0f} s")
        try:
            summary["mine"] = mine_speed(model_file, until=mine_until, rom_options=rom_options)
            say(f"mine: {summary['mine']['realtime_factor_cpu']:.1f}x real time by CPU time")
        except ValidationError as exc:
            summary["mine"] = {"error": str(exc), "realtime_factor_at_least_100": False}
            errors.append(f"mine: {exc}")
        summary["targets"]["mine_realtime_factor_at_least_100"] = \
            summary["mine"]["realtime_factor_at_least_100"]
    if integration_duration is not None:
        say(f"integration test at speed 1 for {integration_duration:.0f} s")
        try:
            summary["integration_test"] = integration_test(
                model_file, Path(out) / "integration_test", duration=integration_duration,
                rom_options=rom_options)
            # beside summary.json, wherever the folder is moved
            summary["integration_test"]["report"] = "integration_test/report.json"
        except ValidationError as exc:
            summary["integration_test"] = {"error": str(exc), "real_time_without_loss": False}
            errors.append(f"integration test: {exc}")
        summary["targets"]["integration_test_real_time_without_loss"] = \
            summary["integration_test"]["real_time_without_loss"]
    return errors
