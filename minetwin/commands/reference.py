"""``minetwin reference``: record a scenario's reference result, compare a rerun with it.

``record SCENARIO --out FILE.csv`` runs the scenario and writes the signals
its ``[reference]`` table names; ``compare SCENARIO FILE.csv`` reruns it,
prints a table of each signal's worst deviation, writes a PNG overlay of
every signal outside its band and exits 0 only if all signals pass (1 if
any fails, 2 on bad input).
"""

from __future__ import annotations

import sys
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "reference", help="record a scenario's reference result or compare a rerun with it",
        description="Reference results for regression tests (FMI cross-check style): record "
                    "the signals a scenario's [reference] table names to a CSV, or rerun the "
                    "scenario and compare each signal with its tolerance band.")
    sub = parser.add_subparsers(dest="reference_command", metavar="ACTION", required=True)

    record = sub.add_parser("record", help="run SCENARIO and write its reference signals to CSV")
    _common(record)
    record.add_argument("--out", type=Path, required=True, help="reference CSV to write")
    record.set_defaults(handler=run_record)

    compare = sub.add_parser("compare", help="rerun SCENARIO and compare with a reference CSV")
    _common(compare)
    compare.add_argument("reference", type=Path, help="reference CSV (from `reference record`)")
    compare.add_argument("--out", type=Path, default=None, metavar="DIR",
                         help="write PNG overlays of failing signals to DIR/overlays "
                              "(default: none written)")
    compare.set_defaults(handler=run_compare)


def _common(parser) -> None:
    parser.add_argument("scenario", type=Path, help="scenario TOML with a [reference] table")
    parser.add_argument("--until", type=float, default=None,
                        help="simulated time [s] (default: reference.until of the scenario, "
                             "for compare the reference's last time)")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default: scenario's)")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE",
                        help="override a scenario value, e.g. --set assets.crusher.fmu=other.fmu "
                             "(VALUE is read as TOML, else as a string); repeatable")
    parser.add_argument("--run-dir", type=Path, default=None,
                        help="keep the run's outputs here (default: a temporary folder)")


def _parse_overrides(items: list[str]) -> dict:
    import tomllib

    from cosim.errors import ValidationError

    overrides = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ValidationError("--set", "KEY=VALUE", f"got {item!r}")
        try:
            value = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError:
            value = text
        overrides[key.strip()] = value
    return overrides


class RunFailed(Exception):
    """The scenario run itself failed (exit code 1)."""


def _run(args, until: float):
    import tempfile

    from cosim.master import CosimulationError
    from minetwin.testing.scenario import run_scenario

    overrides = _parse_overrides(args.overrides)
    try:
        if args.run_dir is not None:
            return run_scenario(args.scenario, until=until, overrides=overrides,
                                seed=args.seed, out=args.run_dir, progress=True)
        with tempfile.TemporaryDirectory(prefix="minetwin-reference-") as tmp:
            run = run_scenario(args.scenario, until=until, overrides=overrides,
                               seed=args.seed, out=Path(tmp), progress=True)
            run.close()
            return run
    except CosimulationError as exc:
        raise RunFailed(f"the run of {args.scenario} failed: {exc}") from exc


def run_record(args) -> int:
    from cosim.errors import ValidationError
    from minetwin.testing.reference import ReferenceResult, ReferenceSpec

    spec = ReferenceSpec.from_scenario(args.scenario)
    until = args.until if args.until is not None else spec.until
    if until is None:
        raise ValidationError("--until", "given, or reference.until in the scenario",
                              f"{args.scenario} has no reference.until")
    try:
        run = _run(args, until)
    except RunFailed as exc:
        print(f"minetwin reference record: {exc}", file=sys.stderr)
        return 1
    reference = ReferenceResult.from_timeseries(run.timeseries, spec.signals)
    path = reference.write(args.out)
    print(f"recorded {len(spec.signals)} signal(s) x {reference.time.size} samples "
          f"(0..{until:g} s) of {args.scenario} to {path}", file=sys.stderr)
    return 0


def run_compare(args) -> int:
    from minetwin.testing.reference import ReferenceResult, ReferenceSpec, compare

    spec = ReferenceSpec.from_scenario(args.scenario)
    reference = ReferenceResult.read(args.reference)
    until = args.until if args.until is not None else float(reference.time[-1])
    try:
        run = _run(args, until)
    except RunFailed as exc:
        print(f"minetwin reference compare: {exc}", file=sys.stderr)
        return 1
    tolerances = {name: spec.tolerance(name) for name in reference.signals}
    report = compare(run.timeseries, reference, tolerances=tolerances)
    print(f"scenario {args.scenario} vs reference {args.reference}")
    print(report.table())
    if report.passed:
        return 0
    if args.out is None:
        print("no overlays written: pass --out DIR to get DIR/overlays/<signal>.png",
              file=sys.stderr)
    else:
        from cosim.plotstyle import run_label

        label = run_label(run.config, scenario=args.scenario.stem, seed=args.seed)
        for path in report.plot_failures(args.out / "overlays", run=label):
            print(f"overlay: {path}")
    print(report.details(), file=sys.stderr)
    return 1
