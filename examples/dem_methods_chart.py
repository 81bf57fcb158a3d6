"""Error of the explicit and the nonsmooth DEM against their cost, and where each fails (issue 22).

Runs the study of ``surrogate/dem/method_study.py`` (its docstring states the
scenes, stiffnesses, reference, observables and failure criteria): a settled
pile, a funnel discharge and an inflow onto a pile, at the soft k_n = 4e7 N/m
and a rock k_n = 1e10 N/m (granite, E = 50 GPa), each by the explicit DEM at
0.25 (the reference, and a replica 1e-6 m apart for the noise floor) to 8
stable steps and by the nonsmooth DEM at 1-20 ms x 10-200 sweeps, plain and
over-relaxed (1.9). The runs
go through ``cosim.batch.run_calls`` on ``--workers`` processes (one core
each).

Writes into ``--out``:

* ``dem_methods.json`` (strict JSON: sizes, criteria, every run's row) and
  ``dem_methods.csv`` (one line per run);
* ``dem_methods_soft.png`` and ``dem_methods_rock.png``: per observable one
  panel of its error against wall seconds per simulated second (log axis),
  explicit as one line over its steps, nonsmooth one line per sweep count
  over its steps (dashed: over-relaxed), failures marked, the noise floor drawn;
* ``failures/RUN/pile_speed.png`` (and grade, residence time): the pile at
  each failure.

Run: ``.venv/bin/python examples/dem_methods_chart.py --out out/dem_methods``
(measured: 4 min 33 s on 2 workers at a load average of 2-4, the runs
7.4 min of one core in all); ``--quick``: fewer settings on smaller scenes,
1.5-4.5 min measured (light to heavy load).
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from cosim import jsonio

PANELS = (
    ("inflow", "angle_error_deg", "angle of repose error [deg]",
     "angle of repose after the inflow"),
    ("funnel", "discharge_rate_error", "discharge rate error [-]",
     "funnel discharge rate (relative)"),
    ("settled", "penetration_ratio_to_reference", "mean penetration / reference's [-]",
     "mean penetration of the settled pile"),
    ("funnel", "tracking_error", "tracking error [-]", "funnel outflow tracking error"),
)
"""(scene, column, y label, panel title) of the chart panels."""

CSV_COLUMNS = ("scene", "stiffness", "normal_stiffness_N_m", "method", "dt_s", "dt_over_stable",
               "iterations", "relaxation", "replica", "reference", "simulated_s", "wall_s_per_simulated_s",
               "mean_sweeps_per_step", "particles", "mean_penetration", "max_penetration",
               "angle_of_repose_deg", "discharge_rate_kg_s", "beverloo_kg_s", "angle_error_deg",
               "discharge_rate_error", "penetration_ratio_to_reference", "tracking_error",
               "failure", "failure_time_s", "failure_reason", "failure_picture")


def progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def write_csv(table: list[dict], path: Path) -> None:
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(CSV_COLUMNS)
        for row in table:
            failure = row["failure"] or {}
            flat = {**row, "failure": failure.get("kind", ""),
                    "failure_time_s": failure.get("time_s", ""),
                    "failure_reason": failure.get("reason", ""),
                    "failure_picture": failure.get("picture", "")}
            writer.writerow(["" if flat.get(c) is None else flat.get(c) for c in CSV_COLUMNS])


def plot(table: list[dict], stiffness: str, k_n: float, path: Path) -> Path:
    """The chart of one stiffness (module docstring)."""
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(13, 9))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, (scene, column, ylabel, what) in zip(axes.flat, PANELS):
        rows = [r for r in table if r["scene"] == scene and r["stiffness"] == stiffness
                and not r["reference"] and r["replica"] == 0]
        finite = [r[column] for r in rows if r[column] is not None]
        top = 1.15 * max(finite) if finite else 1.0
        sweeps = sorted({r["iterations"] for r in rows if r["method"] == "nonsmooth"})
        # a sweep count keeps its colour; over-relaxed, its line is dashed
        series = [("explicit", None, None)] + sorted(
            {("nonsmooth", r["iterations"], r["relaxation"]) for r in rows
             if r["method"] == "nonsmooth"}, key=lambda s: (s[1], s[2]))
        for method, iterations, relaxation in series:
            mine = sorted((r for r in rows if r["method"] == method
                           and r["iterations"] == iterations
                           and r["relaxation"] == relaxation), key=lambda r: r["dt_s"])
            good = [r for r in mine if r[column] is not None and r["wall_s_per_simulated_s"]]
            label = ("explicit, 0.5-8 stable steps" if method == "explicit"
                     else f"nonsmooth, {iterations} sweeps"
                     + (f", over-relaxed {relaxation:g}" if relaxation != 1.0 else "")
                     + ", 1-20 ms")
            colour = colours[0 if method == "explicit" else 1 + sweeps.index(iterations)]
            style = {"color": colour, "marker": "s" if method == "explicit" else (
                "o" if relaxation == 1.0 else "^"), "ms": 5}
            ax.plot([r["wall_s_per_simulated_s"] for r in good], [r[column] for r in good],
                    "-" if relaxation in (None, 1.0) else "--", label=label, **style)
            if method == "explicit":
                for r in good:
                    ax.annotate(f"{r['dt_over_stable']:g}x", (r["wall_s_per_simulated_s"],
                                                               r[column]), fontsize=7)
            elif iterations == sweeps[-1] and relaxation == 1.0:
                for r in good:
                    ax.annotate(f"{r['dt_s'] * 1e3:g} ms", (r["wall_s_per_simulated_s"],
                                                             r[column]), fontsize=7)
        failed = [r for r in rows if r["failure"] is not None and r["wall_s_per_simulated_s"]]
        if failed:
            ax.plot([r["wall_s_per_simulated_s"] for r in failed],
                    [top if r[column] is None else r[column] for r in failed], "x",
                    color="red", ms=9, mew=2, ls="none",
                    label="failed (blow-up, compressed, leaked, jammed; drawn at the top "
                          "when it has no value)")
        floor = next((r["noise_floor"].get(column) for r in rows if r["noise_floor"]), None)
        if floor is not None:
            ax.axhline(floor, color="k", ls="--", lw=0.8,
                       label=f"noise floor (replica 1e-6 m apart): {floor:.3g}")
        if column == "discharge_rate_error":
            ref = next((r for r in table if r["scene"] == scene and r["stiffness"] == stiffness
                        and r["reference"]), None)
            if ref and ref["discharge_rate_kg_s"]:
                gap = abs(ref["beverloo_kg_s"] - ref["discharge_rate_kg_s"]) \
                    / ref["discharge_rate_kg_s"]
                ax.axhline(gap, color="grey", ls=":", lw=1.2,
                           label=f"Beverloo's law against the reference: {gap:.3g}")
        if column == "penetration_ratio_to_reference":
            from surrogate.dem.method_study import COMPRESSION_FACTOR

            ax.axhline(COMPRESSION_FACTOR, color="red", ls=":", lw=1.0,
                       label=f"compression criterion ({COMPRESSION_FACTOR:g} x)")
        ax.set_xscale("log")
        ax.set_xlabel("cost: wall seconds per simulated second [s/s]")
        ax.set_ylabel(ylabel)
        ax.set_title(f"{what} ({scene} scene)")
        plotstyle.legend(ax, fontsize=7)
    plotstyle.title(fig, f"Explicit and nonsmooth DEM: error against cost, k_n = {k_n:.3g} N/m "
                         f"({stiffness}); reference: explicit at 0.25 stable steps")
    fig.tight_layout()
    return plotstyle.save(fig, path)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--quick", action="store_true",
                        help="fewer settings on smaller scenes (a few minutes)")
    parser.add_argument("--workers", type=int, default=2,
                        help="processes running the runs at once, one core each (2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the scenes' disk sizes (0)")
    args = parser.parse_args(argv)
    if args.workers < 1:
        print(f"dem_methods_chart: --workers: must be >= 1 (got {args.workers})",
              file=sys.stderr)
        return 2

    from cosim import batch
    from surrogate.dem import method_study as study

    size = study.QUICK if args.quick else study.FULL
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    with batch.LocalExecutor(args.workers) as executor:
        progress("building the start states")
        paths = study.build_start_states(size, out / "start", executor, seed=args.seed)
        calls = study.plan(paths, size, str(out / "failures"))
        progress(f"{len(calls)} runs on {args.workers} worker(s)")
        rows = batch.run_calls(calls, executor)
    table = study.evaluate(rows, size)
    result = {"command": " ".join(["examples/dem_methods_chart.py", *(argv or sys.argv[1:])]),
              "size": {k: (list(v) if isinstance(v, tuple) else v)
                       for k, v in vars(size).items()},
              "stiffness_N_m": study.STIFFNESSES,
              "rock": {"young_modulus_Pa": study.ROCK_YOUNG_MODULUS,
                       "poisson_ratio": study.ROCK_POISSON,
                       "normal_stiffness_N_m": study.ROCK_STIFFNESS},
              "reference": f"explicit at {study.REFERENCE_FACTOR:g} stable steps",
              "failure_criteria": study.FAILURE_CRITERIA, "runs": table}
    jsonio.write(out / "dem_methods.json", result, indent=1)
    write_csv(table, out / "dem_methods.csv")
    for name, k_n in study.STIFFNESSES.items():
        plot(table, name, k_n, out / f"dem_methods_{name}.png")
    failures = [r for r in table if r["failure"] is not None]
    progress(f"{len(table)} runs, {len(failures)} failed; wrote {out / 'dem_methods.json'}, "
             f"{out / 'dem_methods.csv'} and the charts")
    return 0


if __name__ == "__main__":
    sys.exit(main())
