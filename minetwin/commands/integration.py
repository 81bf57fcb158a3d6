"""``minetwin integration-test``: the paper's integration test with real processes.

Starts ``serve-800xa`` (mock 800xA), ``stockpile`` (OPC UA client + REST)
and ``monitor`` as separate processes on 127.0.0.1, runs for ``--duration``
simulated seconds, freezes the plant clock, lets the stockpile catch up,
stops everything and writes ``DIR/report.json`` and PNG plots.

By default it is the paper's test: the ROM stockpile (the shipped paper-scale
model with its DEM surface layer) holding 1,500 t when the plant starts
(``opcua_server/config/prefilled.toml``). ``--model NAME`` picks another
storage model (``fifo``, ``mixing``, ``dem`` or a plug-in's) and each
``--option KEY=VALUE`` is passed to it (``minetwin stockpile
--model-option``), e.g. ``--model rom --option model=out/rom/model.npz`` for a
ROM of one's own; the options are tried on a stockpile in this process first,
so a bad one fails before anything starts.
The report records the model, its options, the model the stockpile process
says it ran, and the warnings it printed (a ROM extrapolating outside its
training ranges says so).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from cosim import jsonio

MAX_LAG_OK_S = 1.0
"""Largest lag [s of simulation] behind the server's clock still called keeping up."""

PREFILLED_CONFIG = Path(__file__).resolve().parents[2] / "opcua_server" / "config" / "prefilled.toml"
"""The default plant: the mock 800xA's default one with 1,500 t in the pile at the start."""

WARNING_LINE = re.compile(r"^\S+:\d+: (\w+): (.+)$")
"""A line of Python's default warning format: ``file:line: Category: message``."""


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "integration-test", help="run server, stockpile client and monitor; audit the exchange",
        description="The paper's integration test: mock 800xA server, stockpile surrogate and "
                    "monitor as separate processes; writes DIR/report.json (tracking ids lost "
                    "or duplicated, mass balance, lag, step times) and PNG plots. Exit code 1 if "
                    "anything was lost or duplicated or the mass balance is off.")
    parser.add_argument("--duration", type=float, required=True, metavar="S",
                        help="simulated seconds to run")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="simulation seconds per wall second (default 1: real time)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    parser.add_argument("--model", default="rom",
                        help="storage model: rom (default: the shipped paper-scale ROM with its "
                             "DEM surface layer), fifo, mixing, dem or any registered name")
    parser.add_argument("--option", "--model-option", dest="option", action="append", default=[],
                        metavar="KEY=VALUE",
                        help="keyword option of the storage model, repeatable, passed to the "
                             "stockpile as its --model-option (e.g. model=out/rom/model.npz "
                             "for rom); checked before any process starts")
    parser.add_argument("--config", type=Path, default=PREFILLED_CONFIG,
                        help="server configuration TOML (default: opcua_server/config/"
                             "prefilled.toml, 1,500 t in the pile at the start)")
    parser.add_argument("--no-monitor", action="store_true", help="do not start the monitor")
    parser.set_defaults(handler=run)


def run(args) -> int:
    import time
    import urllib.request

    from minetwin.acceptance import INTEGRATION_TEST_MAX_S, check_duration
    from minetwin.commands.stockpile import parse_model_options
    from cosim.errors import ValidationError
    from cosim.storage import storage_class
    from opcua_server.audit import audit
    from minetwin.ports import free_port
    from minetwin.harness import (
        ManagedProcess,
        ServerProcess,
        StockpileProcess,
        drain_and_stop,
        minetwin_command,
        prepare_state,
    )

    check_duration("duration", args.duration, INTEGRATION_TEST_MAX_S)
    if not 0 < args.speed <= 1000:
        raise ValidationError("speed", "in (0, 1000]", f"got {args.speed}")
    storage_class(args.model, field="model")
    storage_options = parse_model_options(args.option, field="option")
    _check_storage(args.model, storage_options)
    from opcua_server.config import load_config, source_names

    try:  # the server would refuse it after the other processes start
        names = source_names(load_config(args.config))
    except ValidationError as exc:
        raise ValidationError("--config", exc.allowed, exc.detail) from None
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    # a previous run in DIR: its logs would be appended to and its state resumed
    for stale in ("ledger.json", "stockpile.summary.json", "stockpile.checkpoint",
                  "server.log", "stockpile.log", "monitor.log"):
        (out / stale).unlink(missing_ok=True)
    state = prepare_state(out / "state")
    processes = []
    monitor_ok = None
    try:
        server = ServerProcess(out, state, speed=args.speed, config=args.config,
                               until=args.duration)
        processes.append(server)
        print(f"integration-test: server {server.url}", file=sys.stderr, flush=True)
        stockpile = StockpileProcess(out, state, server.url, model=args.model,
                                     model_options=args.option, rest=True,
                                     source_names=names)
        processes.append(stockpile)
        print(f"integration-test: stockpile REST {stockpile.rest_url}", file=sys.stderr, flush=True)
        if not args.no_monitor:
            port = free_port()
            monitor = ManagedProcess(minetwin_command() + ["monitor", "--stockpile", stockpile.rest_url,
                                                    "--port", str(port)], out / "monitor.log")
            processes.append(monitor)
        # the server freezes its clock at --duration s of plant time (serve-800xa --until)
        wall = args.duration / args.speed
        start = time.monotonic()
        while not server.clock_frozen() and (elapsed := time.monotonic() - start) < 2 * wall + 60:
            time.sleep(min(5.0, max(wall - elapsed, 0.5)))
            print(f"integration-test: {min(elapsed + 5, wall) * args.speed:.0f} / "
                  f"{args.duration:.0f} s simulated", file=sys.stderr, flush=True)
        if not args.no_monitor:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5) as resp:
                    monitor_ok = resp.status == 200
            except OSError:
                monitor_ok = False
        ledger, summary = drain_and_stop(server, stockpile)
    finally:
        for proc in reversed(processes):
            proc.stop()
    report = audit(ledger, summary)
    report.update({
        "duration_s": ledger["time_s"], "speed": args.speed, "model": args.model,
        "storage_options": storage_options, "stockpile_model": summary["model"],
        "stockpile_warnings": _warnings(out / "stockpile.log"),
        "out_of_training_range_at_end": summary.get("out_of_training_range_now", []),
        "max_lag_s": ledger["max_surrogate_lag_s"],
        "client_max_lag_s": summary["max_lag_s"], "lag_p99_s": summary["lag_p99_s"],
        "first_cycle_lag_s": summary["first_cycle_lag_s"],
        "keeps_up": ledger["max_surrogate_lag_s"] <= MAX_LAG_OK_S * max(args.speed, 1.0),
        "step_time_p99_ms": summary["step_time_p99_ms"],
        "step_time_mean_ms": summary["step_time_mean_ms"],
        "exchange_cycles": summary["cycles"], "exchange_cycle_s": summary["cycle_s"],
        "reconnects": summary["reconnects"],
        "outflow_reports": ledger["outbound_sequence"],
        "duplicate_reports_ignored": ledger["duplicate_reports_ignored"],
        "refusals": ledger["refusals"], "monitor_ok": monitor_ok,
        "plots": _plots(out, ledger, summary, names),
    })
    for message in end_warnings(report, MAX_LAG_OK_S * max(args.speed, 1.0)):
        print(f"{WARNING_PREFIX}{message}", file=sys.stderr, flush=True)
    jsonio.write(out / "report.json", report, indent=2)
    print(jsonio.dumps(report, indent=2))
    passed = (report["tracking_ids_lost"] == 0 and report["tracking_ids_duplicated"] == 0
              and report["mass_balance_rel_error"] < 1e-9 and report["unsent_reports"] == 0)
    return 0 if passed else 1


WARNING_PREFIX = "integration-test: warning: "
"""Starts every warning line the test prints on stderr at its end (a caller that
keeps the test's log, like the demo, shows these lines)."""


def end_warnings(report: dict, max_lag_ok_s: float) -> list[str]:
    """What a user must know about a finished run beyond pass or fail: the
    stockpile fell behind real time, or its ROM ended outside its training range."""
    messages = []
    if not report["keeps_up"]:
        messages.append(f"the stockpile did not keep real time: it lagged up to "
                        f"{report['max_lag_s']:.1f} s of plant time behind the server (more "
                        f"than {max_lag_ok_s:g} s; a loaded machine?); the exchange caught up "
                        "at the end, every bin was exchanged")
    if report["out_of_training_range_at_end"]:
        messages.append("at the end the ROM was outside its training range in "
                        + ", ".join(report["out_of_training_range_at_end"]))
    return messages


def _check_storage(model: str, options: dict) -> None:
    """Build the stockpile with these storage options, give it one bin and step it.

    A bad option (unknown keyword, missing or wrong model file, value out of
    range, a model that cannot take a bin) stops the run with a
    ``ValidationError`` naming the field before any process starts.
    """
    import warnings

    from cosim.errors import ValidationError
    from cosim.storage import check_storage_options
    from surrogate.stockpile import StockpileAsset

    check_storage_options(model, options, field="option")
    try:
        with warnings.catch_warnings():
            # a pile of one bin lies outside any ROM's training range: not an error here
            warnings.simplefilter("ignore")
            asset = StockpileAsset(model, storage_options=options)
            asset.receive_bin(1, 500.0, 0.01, 1.0)
            asset.set_discharge_rate(100.0)
            asset.step(1.0)
    except TypeError as exc:
        raise ValidationError("option", f"keyword options of storage model {model!r}",
                              str(exc)) from None


def _warnings(log: Path) -> list[str]:
    """The distinct warnings (``Category: message``) a process printed, in order."""
    found = []
    for line in log.read_text(errors="replace").splitlines():
        match = WARNING_LINE.match(line)
        if match and (text := f"{match[1]}: {match[2]}") not in found:
            found.append(text)
    return found


def _plots(out: Path, ledger: dict, summary: dict, names: dict | None = None) -> list[str]:
    """stockpile_mass_grade.png and cv301_composition.png; ``names``: display name
    per source index (``opcua_server.config.source_names``), else "source N"."""
    import numpy as np

    from cosim import plotstyle

    plt = plotstyle.pyplot()
    run = plotstyle.run_label(scenario="integration test (OPC UA process simulator)",
                              seed=summary.get("seed"), model=summary.get("model"))
    rows = summary["history"]
    t = np.array([r["time_s"] for r in rows])
    mass = np.array([r["held_mass_kg"] for r in rows])
    grade = np.array([r["grade"] if r["grade"] is not None else np.nan for r in rows])
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    ax1.plot(t, mass / 1e3, label="held mass")
    ax1.set_ylabel("held mass [t]")
    # from zero, with room above: a full pile's flat line is not drawn on the frame
    ax1.set_ylim(0, max(float(np.nanmax(mass, initial=0.0)) / 1e3 * 1.1, 1.0))
    ax2.plot(t, grade * 100, color="tab:green", label="mass-weighted grade")
    ax2.set_ylabel("average grade [%]")
    ax2.ticklabel_format(axis="y", useOffset=False)
    # a pile of 1,500 t barely moves its average grade in a minute: 0.5 %-points at least
    plotstyle.span_at_least(ax2, grade * 100, 0.5)
    ax2.set_xlabel("simulation time [s]")
    for ax in (ax1, ax2):
        plotstyle.legend(ax, loc="upper left")
    plotstyle.title(fig, "Stockpile SP201 (virtual sensors over REST)", run)
    fig.tight_layout()
    first = plotstyle.save(fig, out / "stockpile_mass_grade.png", dpi=100)

    log = ledger["outflow_log"]
    # every source whose ore entered the stockpile, also one none of whose ore has left
    # yet (delivered_by_source counts only ore that has reached the end of CV301)
    sources = sorted({*(str(s) for s in ledger.get("source_of", {}).values()),
                      *(s for row in log for s in row["by_source"])}, key=int)
    times = np.array([row["time_s"] for row in log])
    names = {int(k): v for k, v in (names or {}).items()}

    def named(source: str) -> str:
        return names.get(int(source), "unknown source" if int(source) < 0 else f"source {source}")

    fig, ax = plt.subplots(figsize=(8, 4.5))
    end = max(float(ledger.get("time_s", 0.0)), 1.0)
    # reports the stockpile sends after the server's clock stopped (it lagged) are
    # stamped at the end: a vertical step on the frame; the totals are held on to the
    # right of the end line, so that the stack's height there is what the legend says
    late = sum(sum(row["by_source"].values()) for row in log if row["time_s"] >= end - 1e-9)
    if log:
        cumulative = np.array([[row["by_source"].get(s, 0.0) for s in sources] for row in log])
        cumulative = np.cumsum(cumulative, axis=0) / 1e3
        if late > 0:
            times = np.append(times, end * 1.03)
            cumulative = np.vstack([cumulative, cumulative[-1]])
        ax.stackplot(times, cumulative.T,
                     labels=[f"{named(s)}: {cumulative[-1, j]:.1f} t" for j, s in
                             enumerate(sources)])
    if late > 0:
        plotstyle.mark(ax, end, f"end of the run; right of it: the totals, with {late / 1e3:.1f}"
                                f" t reported after the end (the stockpile lagged)")
    if log:
        plotstyle.legend(ax, loc="upper left")
    ax.set_xlim(0.0, end * 1.03)  # the whole run, not the outflow
    ax.set_xlabel("simulation time [s]")
    ax.set_ylabel("mass loaded onto CV301 [t]")
    plotstyle.title(fig, "Outgoing belt CV301: composition by source (cumulative, stacked)", run)
    fig.tight_layout()
    second = plotstyle.save(fig, out / "cv301_composition.png", dpi=100)
    return [first.name, second.name]
