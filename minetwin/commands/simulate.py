"""``minetwin simulate``: run a mine-simulator scenario and write its results."""

from __future__ import annotations

import sys
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "simulate", help="run a mine-simulator scenario (TOML) and write its results",
        description="Run the 2D mine simulator (sources, haul trucks, jaw crusher, conveyors, "
                    "stockpile, mill; paper section 'Simulator') for a scenario file and write "
                    "DIR/timeseries.parquet (every FMU output and virtual sensor, one row per "
                    "recorded time), DIR/events.sqlite (macro-tracking events), "
                    "DIR/summary.json and DIR/overview.png. Progress goes to stderr.")
    parser.add_argument("scenario", type=Path, help="scenario TOML, e.g. "
                        "examples/step_response.toml")
    parser.add_argument("--until", type=float, default=None, metavar="SECONDS",
                        help="simulated time [s] (default: the scenario's simulation.until_s)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="output folder (created)")
    parser.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    parser.add_argument("--storage-model", default=None, metavar="NAME",
                        help="override the stockpile's storage model (fifo, mixing, ...)")
    parser.add_argument("--model-option", action="append", default=[], metavar="KEY=VALUE",
                        help="keyword option of the stockpile's storage model, repeatable "
                             "(e.g. --storage-model rom --model-option model=out/rom/model.npz);"
                             " replaces the options of every stockpile in the scenario")
    parser.add_argument("--rest-port", type=int, default=None, metavar="PORT",
                        help="serve the stockpile's REST API on 127.0.0.1:PORT while running "
                             "(0: a free port, printed), for `minetwin monitor`")
    parser.add_argument("--realtime-factor", type=float, default=None, metavar="X",
                        help="with --rest-port: pace the run to X simulated s per wall s "
                             "(default: as fast as possible)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(handler=run)


def run(args) -> int:
    from minetwin.commands.stockpile import parse_model_options
    from cosim.errors import ValidationError
    from cosim.master import CosimulationError
    from cosim.scenario import load, run_scenario
    from cosim.storage import storage_class

    if args.until is not None and not args.until > 0:
        raise ValidationError("--until", "> 0 s", f"got {args.until!r}")
    if args.storage_model is not None:
        storage_class(args.storage_model, field="--storage-model")
    if args.rest_port is not None and not 0 <= args.rest_port <= 65535:
        raise ValidationError("--rest-port", "in [0, 65535]", f"got {args.rest_port!r}")
    if args.realtime_factor is not None and args.rest_port is None:
        raise ValidationError("--realtime-factor", "given together with --rest-port")
    config = load(args.scenario)
    if args.model_option:
        options = parse_model_options(args.model_option, field="--model-option")
        from cosim.scenario import assets_of_kind

        for pile in assets_of_kind(config, "stockpile"):
            config["assets"][pile]["options"] = options
    try:
        _, summary = run_scenario(config, args.out, until=args.until, seed=args.seed,
                                  storage_model=args.storage_model, progress=not args.quiet,
                                  before_run=_rest_server(args),
                                  scenario_name=Path(args.scenario).stem)
    except CosimulationError as exc:
        print(f"minetwin simulate: run failed: {exc}", file=sys.stderr)
        return 1
    print(f"simulated {summary['simulated_s']:g} s in {summary['wall_s']:.1f} s "
          f"({summary['realtime_factor']:,.0f}x real time); "
          f"mass balance error {summary['mass_balance_rel_error']:.1e}")
    for name in ("summary.json", "timeseries.parquet", "events.sqlite", "overview.png"):
        print(args.out / name)
    return 0


def _rest_server(args):
    """The hook that serves the stockpile over REST, or None without --rest-port."""
    if args.rest_port is None:
        return None

    def serve(simulation):
        from surrogate.rest import serve_simulation

        rest = serve_simulation(simulation, port=args.rest_port,
                                realtime_factor=args.realtime_factor)
        print(f"stockpile REST on http://127.0.0.1:{rest.port}", file=sys.stderr, flush=True)

    return serve
