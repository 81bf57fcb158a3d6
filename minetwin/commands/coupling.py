"""``minetwin coupling-step``: the largest communication step within a coupling tolerance.

Runs the scenario at a ladder of steps (each the double of the one before), one
batch of runs into ``DIR/runs/<key>`` (skipped when already done), estimates each
declared signal's coupling error at every step by step doubling
(``cosim.analyses.coupling_step``), and picks the largest step within the
tolerance. Writes ``DIR/coupling_step.json`` and ``DIR/coupling_step.png``.
With ``--adaptive`` it also runs the scenario with the step adapted during the run
(``cosim.master.AdaptiveStep``) and reports its steps, its cost and its error
against the finest run beside the fixed 0.5 s step's.
"""

from __future__ import annotations

import sys
from pathlib import Path

from minetwin import executors

DEFAULT_STEPS = "0.125,0.25,0.5,1,2"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "coupling-step",
        help="the largest communication step whose coupling error is within a tolerance",
        description="Run SCENARIO at each --steps communication step (a ladder of "
                    "doublings), estimate the coupling error of each declared signal's "
                    "window means by step doubling (Richardson), and report the largest step "
                    "within the tolerance, the cost of every step, and the error of each "
                    "against the finest run. Signals and tolerance default to the scenario's "
                    "simulation.coupling_signals and simulation.coupling_tolerance. Writes "
                    "DIR/coupling_step.json and DIR/coupling_step.png; runs already in DIR "
                    "are skipped.")
    parser.add_argument("scenario", type=Path,
                        help="scenario TOML, e.g. examples/step_response.toml")
    parser.add_argument("--steps", default=DEFAULT_STEPS, metavar="H1,H2,...",
                        help=f"communication steps [s], each twice the one before "
                             f"({DEFAULT_STEPS})")
    parser.add_argument("--signals", default=None, metavar="A.X,B.Y",
                        help="declared signals (component.output; default: the scenario's "
                             "simulation.coupling_signals)")
    parser.add_argument("--tolerance", type=float, default=None,
                        help="largest relative error of the window means (default: the "
                             "scenario's simulation.coupling_tolerance)")
    parser.add_argument("--window", type=float, default=60.0, metavar="SECONDS",
                        help="window of the means compared [s] (60)")
    parser.add_argument("--until", type=float, default=None, metavar="SECONDS",
                        help="simulated time of each run [s] (default: the scenario's)")
    parser.add_argument("--adaptive", action="store_true",
                        help="also run the scenario with the step adapted during the run "
                             "(simulation.communication_step = \"adaptive\", from 0.5 s "
                             "within the ladder's smallest and largest steps) and report its "
                             "steps, wall time and error against the finest run beside the "
                             "fixed 0.5 s step's")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    executors.add_options(parser, workers=2)
    parser.set_defaults(handler=run)


def _steps(text: str) -> list[float]:
    """The ladder of steps [s], checked before anything runs."""
    from cosim.analyses.coupling_step import check_ladder
    from cosim.errors import ValidationError

    try:
        steps = sorted(float(part) for part in text.split(","))
    except ValueError:
        raise ValidationError("--steps", "numbers [s] separated by commas",
                              f"got {text!r}") from None
    if len(steps) < 2 or not all(0.001 <= h <= 5.0 for h in steps):
        raise ValidationError("--steps", "at least two steps in [0.001, 5] s", f"got {text!r}")
    return check_ladder(steps, "--steps")


def plan(args):
    """The runs (``cosim.batch.Task``), the declared signals and the tolerance."""
    import copy

    from cosim import batch
    from cosim.errors import ValidationError
    from cosim.scenario import load, validate

    from minetwin.commands.sweep import run_point

    steps = _steps(args.steps)
    base = load(args.scenario)
    declared = validate(copy.deepcopy(base))["simulation"]
    signals = ([s.strip() for s in args.signals.split(",") if s.strip()] if args.signals
               else list(declared["coupling_signals"]))
    tolerance = args.tolerance if args.tolerance is not None else declared["coupling_tolerance"]
    if not signals:
        raise ValidationError("--signals", "one or more component.output names (or the "
                              "scenario's simulation.coupling_signals)", "none given")
    if tolerance is None or not 0.0 < tolerance <= 1.0:
        raise ValidationError("--tolerance", "in (0, 1] (or the scenario's "
                              "simulation.coupling_tolerance)", f"got {tolerance!r}")
    if args.until is not None and not args.until > 0:
        raise ValidationError("--until", "> 0 s", f"got {args.until!r}")
    if not args.window >= steps[-1]:
        raise ValidationError("--window", f">= the largest step {steps[-1]:g} s",
                              f"got {args.window!r}")
    tasks = []
    for step in steps:
        config = copy.deepcopy(base)
        simulation = config.setdefault("simulation", {})
        # one recording interval for every run: the window means then average alike
        simulation.update(step_s=step, record_every_s=steps[-1])
        config = validate(config)
        tasks.append(batch.Task(f"step {step:g} s", run_point,
                                {"config": config, "settings": {"simulation.step_s": step},
                                 "until": args.until, "scenario_name": args.scenario.stem},
                                seed=int(config["simulation"]["seed"]), writes_folder=True))
    if args.adaptive:
        if 0.5 not in steps:
            raise ValidationError("--steps", "a ladder holding 0.5 s with --adaptive (the "
                                  "fixed step it is compared with)", f"got {args.steps!r}")
        config = copy.deepcopy(base)
        config.setdefault("simulation", {}).update(
            step_s=0.5, communication_step="adaptive", step_min_s=steps[0],
            step_max_s=steps[-1], record_every_s=steps[-1], coupling_signals=signals,
            coupling_tolerance=float(tolerance))
        config = validate(config)
        tasks.append(batch.Task("adaptive step", run_point,
                                {"config": config,
                                 "settings": {"simulation.communication_step": "adaptive"},
                                 "until": args.until, "scenario_name": args.scenario.stem},
                                seed=int(config["simulation"]["seed"]), writes_folder=True))
    return steps, tasks, signals, float(tolerance)


def run(args) -> int:
    import pandas as pd

    from cosim import batch, jsonio
    from cosim.analyses import coupling_step
    from cosim.plotstyle import run_label

    steps, tasks, signals, tolerance = plan(args)
    args.out.mkdir(parents=True, exist_ok=True)
    with executors.make(args) as executor:
        records = batch.run_batch(tasks, executor, store=args.out, label="coupling-step")
    failed = [r for r in records if r["status"] != "done"]
    for record in failed:
        print(f"minetwin coupling-step: run {record['name']} failed: {record.get('error')}",
              file=sys.stderr)
    if failed:
        return 1
    adaptive_record = records[len(steps)] if len(records) > len(steps) else None
    records = records[:len(steps)]
    runs = {h: pd.read_parquet(Path(r["folder"]) / "timeseries.parquet")
            for h, r in zip(steps, records)}
    until = min(float(r["value"]["simulated_s"]) for r in records)
    costs = {h: float(r["value"]["wall_s"]) / float(r["value"]["simulated_s"])
             for h, r in zip(steps, records)}
    table = coupling_step.coupling_errors(runs, signals, window_s=args.window, until=until)
    chosen = coupling_step.largest_step_within(table, tolerance)
    reference_step = 0.5 if 0.5 in costs else None
    result = {"scenario": str(args.scenario), "signals": signals, "tolerance": tolerance,
              "window_s": args.window, "simulated_s": until, "order_assumed": coupling_step.ORDER,
              "steps": [{"step_s": h, "wall_s_per_s": costs[h],
                         "signals": table[h]} for h in steps],
              "chosen_step_s": chosen,
              "wall_ratio_fixed_0.5_s_to_chosen": (costs[reference_step] / costs[chosen]
                                                   if reference_step and chosen else None)}
    if adaptive_record is not None:
        value = adaptive_record["value"]
        adaptive_run = pd.read_parquet(Path(adaptive_record["folder"]) / "timeseries.parquet")
        result["adaptive"] = {
            "steps": value["communication_steps"],
            "wall_s_per_s": float(value["wall_s"]) / float(value["simulated_s"]),
            "against_finest": coupling_step.errors_against(
                runs[steps[0]], adaptive_run, signals, window_s=args.window, until=until),
            "wall_ratio_fixed_0.5_s_to_adaptive": costs[0.5] / (float(value["wall_s"])
                                                                / float(value["simulated_s"]))}
    jsonio.write(args.out / "coupling_step.json", result, indent=1)
    coupling_step.plot(table, costs, tolerance, chosen, args.out / "coupling_step.png",
                       run=run_label(records[0]["inputs"]["config"],
                                     scenario=args.scenario.stem))
    print(f"{'step [s]':>9} {'wall s/s':>9}  " + "  ".join(f"{s} (estimate / vs finest)"
                                                        for s in signals))
    for h in steps:
        cells = []
        for s in signals:
            row = table[h][s]
            estimate = "-" if row["estimate"] is None else f"{row['estimate']:.4f}"
            cells.append(f"{estimate} / {row['against_finest']:.4f}")
        print(f"{h:>9g} {costs[h]:>9.3g}  " + "  ".join(cells))
    if "adaptive" in result:
        adaptive = result["adaptive"]
        steps_used = adaptive["steps"]
        errors = ", ".join(f"{s} {e:.4f}" for s, e in adaptive["against_finest"].items())
        print(f"adaptive step: {steps_used['count']} steps ({steps_used['min_s']:g}-"
              f"{steps_used['max_s']:g} s, mean {steps_used['mean_s']:.3f} s) against "
              f"{int(round(until / 0.5))} at 0.5 s; {adaptive['wall_s_per_s']:.3g} wall s/s "
              f"against {costs[0.5]:.3g} at 0.5 s (fixed 0.5 s / adaptive = "
              f"{adaptive['wall_ratio_fixed_0.5_s_to_adaptive']:.2f}); error against the "
              f"{steps[0]:g} s run: {errors} (tolerance {tolerance:g})")
    if chosen is None:
        print(f"minetwin coupling-step: no step above {steps[0]:g} s is within {tolerance:g}; "
              "add finer steps to --steps", file=sys.stderr)
        return 1
    saved = result["wall_ratio_fixed_0.5_s_to_chosen"]
    print(f"chosen step {chosen:g} s: the largest within {tolerance:g} for {signals}"
          + (f"; wall time of the fixed 0.5 s step / chosen = {saved:.2f}" if saved else ""))
    print(f"wrote {args.out / 'coupling_step.json'} and {args.out / 'coupling_step.png'}",
          file=sys.stderr)
    return 0
