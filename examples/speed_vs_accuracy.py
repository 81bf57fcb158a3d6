"""Speed against accuracy of the stockpile fidelity ladder, and the pile pictures.

Issue 10 / paper sections "Integration test" and "Predicting the properties
of the mill feed": on a held-out scenario (300 s, rates and pile state not
in the ROM's training design) every storage model is scored by its tracking
error (mean total-variation distance of the 30 s outflow compositions per
15 t lot) against a fine-step DEM (dt = stable_dt / 4) and placed against
its wall seconds per simulated second (log axis):

- FIFO and perfect mixing;
- the ROM at several POD mode counts, in two families: surface layer by
  resolved DEM of the falling and spreading particles (``surface="dem"``,
  the default) and by the sandpile rule (``surface="rule"``);
- the DEM at the time-step ladder ``DT_FACTORS`` x stable_dt (forced steps
  above 1). A step that blows the DEM up (``surrogate.rom.doe.instability``:
  a disk leaving the container, faster than twice the free-fall speed, or
  overlapping by half a diameter) is stopped there and drawn as an X at the
  cost it reached, labelled "unstable";
- the nonsmooth DEM (the paper's method: Servin, Wang, Lacoursiere and Bodin
  2014; ``surrogate.dem.nonsmooth``) from the same start at the settings
  ``NONSMOOTH_SETTINGS``: the paper's 11 ms and 100 projected Gauss-Seidel
  sweeps, fewer sweeps, a longer step, and over-relaxed (``solver_relaxation``).

The DEM's chaos floor (two DEM runs 1e-6 m apart) is drawn as a line.

Writes into --out: ``speed_vs_accuracy.png``, ``speed_vs_accuracy.json``
(the points) and ``pile_fields.png`` (velocity, grade and hardness fields of
the DEM and the default ROM at the middle of the held-out run, the paper's
figure "pileDistribution").

``--scenario`` picks the held-out scenario (default ``heldout``, 200 kg/s;
``heldout_q1200`` and ``heldout_q1500`` run at the paper's throughput, where
the DEM's chaos floor is lower and the chart separates the models better).
The data build runs every held-out scenario that ``minetwin rom evaluate``
scores (``surrogate.rom.doe.HELDOUT_SCENARIOS``) and the DEM ladder of the
chosen one.

Run (from the repository root; the first run builds the DEM data, about
10-20 minutes on 2 cores, later runs reuse it)::

    .venv/bin/python examples/speed_vs_accuracy.py --data examples/out/rom_data --out examples/out
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

from cosim import jsonio

DT_FACTORS = (0.25, 0.5, 2.0, 4.0, 6.0, 8.0)
"""DEM time steps run besides the default, as multiples of stable_dt; the
smallest is the reference. Above 1 the steps are forced (a stability study).
Measured on the held-out scenarios: 2 stable_dt runs the 300 s; at 4 the pile
"boils" (ten times the kinetic energy of the stable step) until a disk passes
the 1 m side wall (after 109 s at 200 kg/s, 195 s at 1.5 t/s); 6 and 8 blow up
within seconds (disks flung out of the container). The guard stops those runs
and the chart marks them "unstable" at the cost they reached. (Before the
guard, an unstable run went on at a crawl.)"""

NONSMOOTH_SETTINGS = ((0.011, 100, 1.0), (0.011, 25, 1.0), (0.02, 100, 1.0),
                      (0.011, 100, 1.9))
"""``(step [s], sweeps, solver_relaxation)`` of the nonsmooth DEM points: the
paper's setting first."""


def nonsmooth_runs() -> tuple:
    """``(file name, DemConfig changes)`` of the nonsmooth DEM runs."""
    runs = []
    for step, sweeps, relaxation in NONSMOOTH_SETTINGS:
        name = f"dem_nonsmooth_{step * 1e3:g}ms_{sweeps}it" + (
            f"_relaxed{relaxation:g}" if relaxation != 1.0 else "")
        runs.append((name, {"method": "nonsmooth", "nonsmooth_dt": step,
                            "solver_iterations": sweeps, "solver_relaxation": relaxation}))
    return tuple(runs)


def nonsmooth_label(changes: dict) -> str:
    return (f"{changes['nonsmooth_dt'] * 1e3:g} ms, {changes['solver_iterations']} sweeps"
            + (f", over-relaxed {changes['solver_relaxation']:g}"
               if changes["solver_relaxation"] != 1.0 else ""))


MODE_COUNTS = (2, 4, 8, 16)
"""POD mode counts (mass and velocity) of the ROM points."""

SURFACES = ("dem", "rule")
"""ROM surface-layer families on the chart (``RomStorage(surface=...)``)."""


def progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def rom_models(ev, data):
    """``(label, model, is_default)`` for each mode count and the
    cross-validated default model (``evaluate.train``)."""
    default = ev.train(data)
    chosen = (default.n_mass_modes, default.n_velocity_modes)
    models = []
    for modes in MODE_COUNTS:
        if (modes, modes) == chosen:
            models.append((f"{modes} modes (default)", default, True))
        else:
            models.append((f"{modes} modes", ev.train(data, n_mass_modes=modes,
                                                      n_velocity_modes=modes), False))
    if chosen not in [(m, m) for m in MODE_COUNTS]:
        models.append((f"{chosen[0]}/{chosen[1]} modes (default)", default, True))
    return models


def plot_ladder(result: dict, path) -> None:
    """The speed-vs-accuracy chart of ``result`` (the ``speed_vs_accuracy.json``
    content) as a PNG at ``path``."""
    from cosim import plotstyle
    from surrogate.rom import doe

    plt = plotstyle.pyplot()
    points, floor = result["points"], result["dem_noise_floor"]
    fine_wall = result["reference_wall_s_per_simulated_s"]
    reference_factor = result["reference_dt_factor"]
    scenario = next(s for s in doe.HELDOUT_SCENARIOS if s.name == result["scenario"])
    colours = {"fifo": "tab:red", "mixing": "tab:orange", "rom_dem": "tab:blue",
               "rom_rule": "tab:purple", "dem": "tab:green", "dem_nonsmooth": "tab:brown"}
    top = 1.08  # unstable runs have no score: their X sits above the scale
    fig, ax = plt.subplots(figsize=(9, 6))
    for p in points:
        if p["kind"] in ("fifo", "mixing"):
            ax.scatter(p["wall_s_per_simulated_s"], p["tracking_error"],
                       color=colours[p["kind"]], s=40, zorder=3)
            ax.annotate(p["label"], (p["wall_s_per_simulated_s"], p["tracking_error"]),
                        textcoords="offset points", xytext=(7, -3), fontsize=8)
    # the families (ROM per surface layer, in mode order; DEM, in step order) lie
    # too close for a label per point: one line each, and a list (setting: error)
    # beside it
    scored = [p for p in points if not p.get("unstable")]
    legend_of = {"rom_dem": "ROM, surface layer by DEM (POD modes, * cross-validated)",
                 "rom_rule": "ROM, surface layer by sandpile rule",
                 "dem": "DEM at a time step (x stable_dt)",
                 "dem_nonsmooth": "nonsmooth DEM (step, sweeps)"}
    families = (
        ("rom_dem", "o", 1, "modes: error", lambda p: p["modes"],
         lambda p: "/".join(str(m) for m in dict.fromkeys(p["modes"]))
         + ("*" if "default" in p["label"] else "")),
        ("rom_rule", "s", -1, "modes: error", lambda p: p["modes"],
         lambda p: "/".join(str(m) for m in dict.fromkeys(p["modes"]))
         + ("*" if "default" in p["label"] else "")),
        ("dem", "o", -1, "dt / stable_dt: error", lambda p: p["dt_factor"],
         lambda p: f"{p['dt_factor']:g}"),
        # settings, not a ladder: points without a line
        ("dem_nonsmooth", "D", 1, "nonsmooth: error", lambda p: p["wall_s_per_simulated_s"],
         lambda p: p["setting"]))
    for kind, marker, side, title, order, name in families:
        family = sorted((p for p in scored if p["kind"] == kind), key=order)
        if not family:
            continue
        x = [p["wall_s_per_simulated_s"] for p in family]
        y = [p["tracking_error"] for p in family]
        ax.plot(x, y, color=colours[kind], marker=marker, ms=6, zorder=3,
                lw=0.0 if kind == "dem_nonsmooth" else 0.8, label=legend_of[kind])
        rows = [f"{name(p)}: {p['tracking_error']:.2f}" for p in family]
        anchor = (max(x) if side > 0 else min(x), float(np.mean(y)))
        ax.annotate(f"{title}\n" + "\n".join(rows), anchor, textcoords="offset points",
                    xytext=(10 * side, 0), ha="left" if side > 0 else "right", va="center",
                    fontsize=7, color=colours[kind], zorder=4,
                    bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "none",
                          "alpha": 0.85})
    unstable = [p for p in points if p.get("unstable")]
    for k, p in enumerate(sorted(unstable, key=lambda p: p["wall_s_per_simulated_s"])):
        ax.scatter(p["wall_s_per_simulated_s"], top, color=colours[p["kind"]], marker="x",
                   s=60, zorder=3)
        # labels stacked below the row of Xs, each with a leader to its X
        what = (f"dt = {p['dt_factor']:g} stable_dt" if p["kind"] == "dem"
                else f"nonsmooth {p['setting']}")
        ax.annotate(f"{what}: unstable at "
                    f"{p['unstable_at_s']:.3g} s", (p["wall_s_per_simulated_s"], top),
                    textcoords="offset points", xytext=(-20, -14 * (k + 1)), ha="right",
                    fontsize=7, arrowprops={"arrowstyle": "-", "lw": 0.5, "color": "grey"})
    ax.scatter(fine_wall, 0.0, color=colours["dem"], marker="*", s=90, zorder=3,
               label=f"reference: DEM dt = {reference_factor:g} stable_dt")
    ax.scatter([], [], color=colours["dem"], marker="x",
               label="DEM blown up (the guard stopped it): cost reached")
    ax.axhline(floor, color="grey", ls="--", lw=1,
               label=f"DEM chaos floor (1e-6 m perturbation): {floor:.2f}")
    ax.axhline(0.10, color="black", ls=":", lw=1, label="target 0.10")
    ax.axhline(1.0, color="grey", ls="-", lw=0.5, label="error 1: nothing tracked")
    ax.axvline(1.0, color="grey", ls="-", lw=0.5, label="real time")
    ax.set_xscale("log")
    ax.set_ylim(-0.02, top + 0.04)
    ax.set_xlabel("wall time per simulated time, one core [s/s] (1 = real time)")
    ax.set_ylabel("tracking error vs fine-step DEM, mean TV distance over 30 s windows [-]")
    plotstyle.title(fig, "Stockpile fidelity ladder: what each second of compute buys",
                    f"held-out scenario {result['scenario']} ({scenario.duration:g} s, "
                    f"{scenario.fill / 1e3:g} t pile, {scenario.inflow_rate:g} kg/s in, "
                    f"{scenario.discharge_rate:g} kg/s out), storage models as in the legend")
    ax.legend(loc="center right", fontsize=7)
    fig.tight_layout()
    plotstyle.save(fig, path, dpi=130)


def plot_fields(rows: dict, grid, time_s: float, scenario: str, path) -> None:
    """pile_fields.png: speed [m/s], grade [%] and hardness [-] of each storage
    model in ``rows`` (name -> fields ``mass`` (ny, nx) [kg], ``velocity``
    (ny, nx, 2) [m/s], ``grade`` [-], ``hardness`` [-]) on the ROM's ``grid``, at ``time_s``."""
    from cosim import plotstyle

    extent = (grid.x_min, grid.x_max, grid.y_min, grid.y_max)
    fig, axes = plotstyle.pyplot().subplots(len(rows), 3, figsize=(13, 2.6 * len(rows)),
                                            sharex=True, sharey=True, squeeze=False)
    for r, (name, f) in enumerate(rows.items()):
        empty = f["mass"] <= 0
        speed = np.where(empty, np.nan, np.linalg.norm(f["velocity"], axis=-1))
        panels = (("speed [m/s]", speed, "viridis", None),
                  ("grade [%]", np.where(empty, np.nan, 100 * f["grade"]), "magma", (20, 80)),
                  ("hardness [-]", np.where(empty, np.nan, f["hardness"]), "coolwarm", (1, 2)))
        for c, (title, values, cmap, lim) in enumerate(panels):
            ax = axes[r, c]
            im = ax.imshow(values, origin="lower", extent=extent, cmap=cmap, aspect="equal",
                           vmin=None if lim is None else lim[0],
                           vmax=None if lim is None else lim[1])
            if c == 0:
                x, y = grid.centres()
                v = np.where(empty[..., None], np.nan, f["velocity"])
                ax.quiver(x, y, v[..., 0], v[..., 1], color="white", scale=8, width=0.002)
            ax.set_title(f"{name}: {title}", fontsize=9)
            fig.colorbar(im, ax=ax, shrink=0.7, label=title)
    # shared axes: the tick labels show on the bottom row and the left column only
    for ax in axes[-1, :]:
        ax.set_xlabel("x [m]")
    for ax in axes[:, 0]:
        ax.set_ylabel("y [m]")
    plotstyle.title(fig, f"Pile fields at t = {time_s:g} s (the funnel zone drains in the near "
                    "future)", f"held-out scenario {scenario}, storage models "
                    f"{' and '.join(rows)}")
    fig.tight_layout()
    plotstyle.save(fig, path, dpi=120)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default="examples/out/rom_data", help="DOE directory")
    parser.add_argument("--out", default="examples/out", help="output directory")
    parser.add_argument("--quick", action="store_true", help="small training design")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scenario", default="heldout",
                        help="held-out scenario of the chart (heldout, heldout_q1200, "
                             "heldout_q1500)")
    parser.add_argument("--workers", type=int, default=2,
                        help="processes running independent DEM runs (2)")
    args = parser.parse_args(argv)

    from surrogate.rom import doe

    names = [s.name for s in doe.HELDOUT_SCENARIOS]
    if args.scenario not in names:
        print(f"speed_vs_accuracy: --scenario: must be one of {names} (got {args.scenario!r})",
              file=sys.stderr)
        return 2
    if args.workers < 1:
        print(f"speed_vs_accuracy: --workers: must be >= 1 (got {args.workers})",
              file=sys.stderr)
        return 2

    from surrogate.rom import evaluate as ev
    from surrogate.rom import metrics

    data, out = Path(args.data), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ev.build_data(data, quick=args.quick, seed=args.seed, progress=progress,
                  reference_dt_factors=DT_FACTORS, workers=args.workers,
                  dt_ladder_scenarios=(args.scenario,), method_runs=nonsmooth_runs())
    heldout = data / args.scenario
    reference_factor = min(DT_FACTORS)
    fine = ev.load_run(heldout / f"dem_dt{reference_factor:g}.npz")
    if int(fine.get("unstable", 0)):
        print(f"speed_vs_accuracy: the reference DEM (dt = {reference_factor:g} stable_dt) "
              f"blew up: {fine['unstable_reason']}", file=sys.stderr)
        return 1
    reference = ev.outflow_of(fine)
    t0 = float(fine["t0"])
    t1 = t0 + ev.scenario_duration(heldout)
    points = []

    def add(label, kind, outflow, wall, **extra):
        points.append({"label": label, "kind": kind,
                       "tracking_error": metrics.tracking_error(outflow, reference, t0, t1),
                       "wall_s_per_simulated_s": wall / (t1 - t0), **extra})
        progress(f"{label}: {points[-1]}")

    for name in ("fifo", "mixing"):
        outflow, wall, _ = ev.run_storage(name, heldout)
        add(name.upper() if name == "fifo" else "perfect mixing", name, outflow, wall)
    captured = {}
    middle = int((t1 - t0) // 2)

    def capture(k, time, storage):
        if k == middle:
            captured.update(storage.fields(), time=time)

    models = rom_models(ev, data)
    for surface in SURFACES:
        for label, model, is_default in models:
            options = {"surface": surface}
            keep_fields = is_default and surface == SURFACES[0]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ev.run_storage("rom", heldout, model, options=options)  # compile, warm up
                outflow, wall, _ = ev.run_storage("rom", heldout, model, options=options,
                                                  on_step=capture if keep_fields else None)
            add(f"ROM {surface} {label}", f"rom_{surface}", outflow, wall,
                modes=[model.n_mass_modes, model.n_velocity_modes], surface=surface)
    def add_dem(label, kind, run, **extra):
        """A DEM run's point; one the guard stopped has no score: its cost until then."""
        if not int(run.get("unstable", 0)):
            add(label, kind, ev.outflow_of(run), float(run["wall_s"]), **extra)
            return
        reached = float(run["unstable_at"])
        points.append({"label": f"{label}: unstable at {reached:.3g} s", "kind": kind, **extra,
                       "unstable": True, "unstable_at_s": reached,
                       "why": str(run["unstable_reason"]), "tracking_error": None,
                       "wall_s_per_simulated_s": float(run["wall_s"]) / max(reached, 1e-9)})
        progress(f"{label}: {points[-1]}")

    for factor in sorted({1.0, *DT_FACTORS} - {reference_factor}):
        run = ev.load_run(heldout / ("dem.npz" if factor == 1.0 else f"dem_dt{factor:g}.npz"))
        add_dem(f"DEM dt = {factor:g} stable_dt", "dem", run, dt_factor=factor)
    for name, changes in nonsmooth_runs():
        setting = nonsmooth_label(changes)
        add_dem(f"nonsmooth DEM {setting}", "dem_nonsmooth",
                ev.load_run(heldout / f"{name}.npz"), setting=setting, solver=changes)
    dem = ev.load_run(heldout / "dem.npz")
    floor = metrics.tracking_error(ev.outflow_of(ev.load_run(heldout / "dem_perturbed.npz")),
                                   ev.outflow_of(dem), t0, t1)
    fine_wall = float(fine["wall_s"]) / (t1 - t0)
    result = {"scenario": args.scenario,
              "reference": f"DEM dt = {reference_factor:g} stable_dt "
                           f"({fine_wall:.3g} wall s per simulated s)",
              "reference_dt_factor": reference_factor,
              "reference_wall_s_per_simulated_s": fine_wall,
              "dem_noise_floor": floor, "points": points}
    jsonio.write(out / "speed_vs_accuracy.json", result, indent=1)
    print(jsonio.dumps(result, indent=1))

    plot_ladder(result, out / "speed_vs_accuracy.png")

    grid = models[0][1].grid
    k = middle
    rows = {"DEM": {"mass": dem["field_mass"][k], "velocity": dem["field_velocity"][k],
                    "grade": dem["field_grade"][k], "hardness": dem["field_hardness"][k]},
            "ROM (default modes)": captured}
    plot_fields(rows, grid, k, args.scenario, out / "pile_fields.png")
    progress(f"wrote {out / 'speed_vs_accuracy.png'} and {out / 'pile_fields.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
