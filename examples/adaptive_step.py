"""Adaptive communication step against the fixed 0.5 s step: steps, wall time, error.

Runs ``examples/step_response.toml`` (or ``--scenario``) at a fine fixed step (the
reference, 0.125 s), then ``--pairs`` times the fixed 0.5 s step and the adaptive
step (``simulation.communication_step = "adaptive"``, 0.125-2 s, ``cosim.master.
AdaptiveStep``) alternately in one process, so that the load of the machine
weighs on both alike. Prints each pair's wall and CPU times, the median ratios
fixed / adaptive (> 1: the adaptive run is faster; CPU time is the fairer figure
on a shared machine), both runs' numbers of steps,
and each declared signal's error against the reference (the largest difference
of its 60 s window means relative to its scale, as ``minetwin coupling-step``),
and writes them to ``--out``/adaptive_step.json::

    .venv/bin/python examples/adaptive_step.py --out out/adaptive_step
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
from pathlib import Path

from cosim import jsonio
from cosim.analyses.coupling_step import errors_against
from cosim.scenario import load, run_scenario

SIGNALS = ["crusher_fmu.power", "mill_fmu.power"]
ADAPTIVE = {"step_s": 0.5, "communication_step": "adaptive", "step_min_s": 0.125,
            "step_max_s": 2.0}


def run(config: dict, **simulation):
    """(time series, summary, wall s, CPU s) of one run of ``config`` with ``simulation``
    set."""
    config = copy.deepcopy(config)
    config["simulation"].update(simulation)
    start, cpu_start = time.perf_counter(), time.process_time()
    sim, summary = run_scenario(config)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    series = sim.timeseries
    sim.close()
    return series, summary, wall, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", type=Path,
                        default=Path(__file__).with_name("step_response.toml"))
    parser.add_argument("--tolerance", type=float, default=0.15,
                        help="simulation.coupling_tolerance [-] (0.15)")
    parser.add_argument("--pairs", type=int, default=5, help="alternated A/B pairs (5)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    base = load(args.scenario)
    # one recording interval (the largest adaptive step) for every run
    base["simulation"].update(record_every_s=2.0, coupling_signals=SIGNALS,
                              coupling_tolerance=args.tolerance)
    until = float(base["simulation"].get("until_s", 1200.0))
    reference, _, _, _ = run(base, step_s=0.125)
    pairs = []
    for _ in range(args.pairs):
        fixed, fixed_summary, fixed_wall, fixed_cpu = run(base, step_s=0.5)
        adaptive, summary, adaptive_wall, adaptive_cpu = run(base, **ADAPTIVE)
        pairs.append({"fixed_wall_s": fixed_wall, "adaptive_wall_s": adaptive_wall,
                      "fixed_cpu_s": fixed_cpu, "adaptive_cpu_s": adaptive_cpu})
        print(f"fixed 0.5 s {fixed_wall:.2f} s wall, {fixed_cpu:.2f} s CPU; adaptive "
              f"{adaptive_wall:.2f} s wall, {adaptive_cpu:.2f} s CPU")
    ratio = statistics.median(p["fixed_wall_s"] / p["adaptive_wall_s"] for p in pairs)
    cpu_ratio = statistics.median(p["fixed_cpu_s"] / p["adaptive_cpu_s"] for p in pairs)
    result = {
        "scenario": str(args.scenario), "tolerance": args.tolerance, "simulated_s": until,
        "fixed_steps": fixed_summary["communication_steps"],
        "adaptive_steps": summary["communication_steps"],
        "fixed_error": errors_against(reference, fixed, SIGNALS, window_s=60.0, until=until),
        "adaptive_error": errors_against(reference, adaptive, SIGNALS, window_s=60.0,
                                         until=until),
        "pairs": pairs, "median_wall_ratio_fixed_to_adaptive": ratio,
        "median_cpu_ratio_fixed_to_adaptive": cpu_ratio}
    args.out.mkdir(parents=True, exist_ok=True)
    jsonio.write(args.out / "adaptive_step.json", result, indent=1)
    steps = result["adaptive_steps"]
    print(f"steps: fixed {result['fixed_steps']['count']}, adaptive {steps['count']} "
          f"({steps['min_s']:g}-{steps['max_s']:g} s, mean {steps['mean_s']:.3f} s)")
    for name in ("fixed", "adaptive"):
        print(f"{name} error against 0.125 s: " + ", ".join(
            f"{s} {e:.4f}" for s, e in result[f"{name}_error"].items()))
    print(f"median wall time fixed 0.5 s / adaptive: {ratio:.2f}; CPU time: {cpu_ratio:.2f}")


if __name__ == "__main__":
    main()
