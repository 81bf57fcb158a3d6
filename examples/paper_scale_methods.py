"""Both DEM methods beside FIFO, mixing and the ROM, at the paper's scale.

On the held-out paper-scale scenes (a 17,500-disk, 1.47 kt pile, 180 s at
1.2 and 2 t/s in and out, and 1.5 t/s out with 0.7 t/s in), every model's
tracking error (mean total-variation distance of the 30 s outflow
compositions per 15 t lot, against each explicit DEM replica of the scene,
averaged) is drawn against its compute per simulated second:

- FIFO, perfect mixing and the shipped ROM: the shipped evaluation
  (``surrogate/rom/data/fidelity/paper_heldout_evaluation.json``, wall time of
  each model's run on one core);
- the explicit DEM at its design step (0.16 t_c): its error is its noise
  floor (its replicas against each other), its cost the CPU time of its runs
  (``surrogate/rom/data/paper_heldout/manifest.json``);
- the nonsmooth DEM (11 ms, 100 projected Gauss-Seidel sweeps, Servin et al.
  2014) where its runs of the same scenes finished
  (``surrogate.rom.method_score``; the design ``paper_heldout_nonsmooth``); a
  run the blow-up guard stopped is an X at error 1 at its cost until then, with
  the time it lasted; a run whose feeder delivered under 0.9 of the explicit
  replicas' mass (``method_score.JAM_DELIVERED_SHARE``) is marked jammed.

A method design with several runs of a scene (``paper_rock_nonsmooth`` runs three,
start states 1e-6 m apart, as the explicit replicas) is scored run by run: its
point is the mean, its bar spans every run against every explicit replica, and
the scene picture draws every run.

``--method-data`` may be repeated (the same scenes run at other settings, e.g.
``minetwin rom design --design paper_rock_nonsmooth --set solver_iterations=200``):
each is one more point per scene.

Per scored scene and method, ``scene_<scene>_<settings>.png`` (e.g.
``scene_heldout_q2000_nonsmooth_11ms_100sweeps.png``) shows the discharged mass over time
(the method, every explicit replica, the set point) and the pile at the end
(areal mass on the ROM grid) of explicit replica 0 and of the method: where a
jam shows.

``--reference`` takes another explicit design, e.g. the rock-stiffness scene
(``paper_rock``, 20 s: score it with ``--window 5``); scenes the ROM evaluation
does not hold get the DEM points only.

DEM costs are CPU seconds: those runs shared a loaded machine, and their wall
time says more about the load than about the method.

Run the nonsmooth design first (about 16 CPU s per simulated second, 45-50 CPU
minutes a scene; resumable)::

    .venv/bin/minetwin rom design --design paper_heldout_nonsmooth --work WORK --workers 1
    .venv/bin/minetwin rom design --design paper_heldout_nonsmooth --work WORK --export --data NS
    .venv/bin/python examples/paper_scale_methods.py --method-data NS --out DIR

Writes ``paper_scale_methods.json`` and ``paper_scale_methods.png`` into
``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from cosim import jsonio
from cosim.errors import ValidationError
from surrogate.rom.method_score import BULK_DISTANCE, CREEP_FACTOR, bulk_speed, score_dem_method
from surrogate.rom.metrics import WINDOW_S

ROOT = Path(__file__).resolve().parents[1]
EVALUATION = ROOT / "surrogate" / "rom" / "data" / "fidelity" / "paper_heldout_evaluation.json"
REFERENCE = ROOT / "surrogate" / "rom" / "data" / "paper_heldout"


def label_of(methods: dict) -> str:
    """The method and its settings, e.g. "nonsmooth DEM, 11 ms, 100 sweeps" (with ",
    over-relaxed 1.9" when its solver over-relaxes)."""
    settings = methods["method_settings"]
    if methods["method"] != "nonsmooth":
        return f"{methods['method']} DEM"
    relaxation = settings.get("solver_relaxation", 1.0)
    return (f"nonsmooth DEM, {settings['nonsmooth_dt'] * 1e3:g} ms, "
            f"{settings['solver_iterations']} sweeps"
            + (f", over-relaxed {relaxation:g}" if relaxation != 1.0 else ""))


def slug_of(methods: dict) -> str:
    """``label_of`` as a file name part, e.g. "nonsmooth_11ms_100sweeps"."""
    return "_".join(part.strip().replace(" DEM", "").replace(" ", "")
                    for part in label_of(methods).split(","))


def points(evaluation: dict, runs: list[dict]) -> dict:
    """Per scene: ``[{"model", "tracking_error", "cost_s_per_s", "cost_kind"}]``: the
    storage models where the evaluation holds the scene, the explicit DEM (its noise
    floor), then each scored method (``runs``: ``score_dem_method`` results against
    the same reference) with its ``label``."""
    out = {}
    explicit_costs = runs[0]["explicit_costs"]
    scenes = [s for s in explicit_costs
              if any(s in m["scenes"] or s in m["failed"] for m in runs)
              or s in evaluation["scenarios"]]
    for scene in scenes:
        row = evaluation["scenarios"].get(scene)
        rows = [] if row is None else [
            {"model": name, "tracking_error": row["tracking_error"][name],
             "cost_s_per_s": row["wall_s_per_simulated_s"][name], "cost_kind": "wall"}
            for name in ("fifo", "mixing", "rom")]
        scored = [m["scenes"][scene] for m in runs if scene in m["scenes"]]
        floor = (scored[0]["tracking_error_dem_noise_floor"] if scored
                 else None if row is None else row["tracking_error_dem_noise_floor"])
        explicit_cost = explicit_costs.get(scene)
        rows.append({"model": "dem_explicit", "tracking_error": floor,
                     "cost_s_per_s": (explicit_cost["cpu_s_per_simulated_s"]
                                      if explicit_cost and floor is not None else None),
                     "cost_kind": "cpu"})
        for index, methods in enumerate(runs):
            common = {"model": f"dem_{methods['method']}", "label": label_of(methods),
                      "index": index, "cost_kind": "cpu"}
            method_row = methods["scenes"].get(scene)
            failed = methods["failed"].get(scene)
            if method_row is not None:
                rows.append({**common, "tracking_error": method_row["tracking_error"],
                             "spread": method_row["tracking_error_spread"],
                             "cost_s_per_s": method_row["method_cost"]["cpu_s_per_simulated_s"],
                             "jammed": method_row["jammed"],
                             "creeping": method_row["creeping"],
                             "bulk_speed_m_s": method_row["bulk_speed_m_s"],
                             "discharged_kg": method_row["discharged_kg"],
                             "explicit_discharged_kg": method_row["explicit_discharged_kg"]})
            elif failed is not None:  # no outflow to score: where and when it blew up
                rows.append({**common, "tracking_error": None,
                             "blew_up_after_s": failed["after_s"], "reason": failed["reason"],
                             "cost_s_per_s": failed["method_cost"]["cpu_s_per_simulated_s"]})
        out[scene] = rows
    return out


FLOOR_MARGIN = 0.05
"""Error above the explicit DEM's noise floor [-] within which another DEM method
counts as accurate (the method comparison's goal)."""

METHOD_COLOURS = ("tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan", "tab:gray")
METHOD_MARKERS = ("D", "v", "^", "<", ">", "P")

BLOWN_UP_ROW = 1.0
"""Where a run that blew up is drawn (it has no tracking error): error 1, nothing
tracked."""


def plot(result: dict, path: Path, window: float) -> None:
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    scenes = list(result["points"])
    # one scene (the rock scene) still needs room for the legend below it
    fig, axes = plt.subplots(1, len(scenes), figsize=(max(5 * len(scenes), 10), 4.6),
                             sharey=True,
                             squeeze=False)
    style = {"fifo": ("tab:red", "o", "FIFO"), "mixing": ("tab:orange", "o", "perfect mixing"),
             "rom": ("tab:blue", "o", "ROM (shipped)"),
             "dem_explicit": ("tab:green", "s", "explicit DEM, 0.16 t_c (its noise floor)")}
    drawn = [p for scene in scenes for p in result["points"][scene]
             if p["cost_s_per_s"] is not None]
    # the error axis shows every point: up to the blow-up row only if a run blew up
    top = (BLOWN_UP_ROW + 0.08 if any(p["tracking_error"] is None for p in drawn)
           else max(0.3, 1.15 * max((p.get("spread", {}).get("max", p["tracking_error"])
                                     for p in drawn), default=0.0)))
    for ax, scene in zip(axes[0], scenes):
        for p in result["points"][scene]:
            if p["cost_s_per_s"] is None:
                continue
            colour, marker, label = style.get(p["model"]) or (
                METHOD_COLOURS[p["index"] % len(METHOD_COLOURS)],
                METHOD_MARKERS[p["index"] % len(METHOD_MARKERS)], p["label"])
            if p["tracking_error"] is None:
                ax.scatter(p["cost_s_per_s"], BLOWN_UP_ROW, color=colour, marker="x", s=70,
                           zorder=3, label=f"{label}: blew up (cost until then)")
                ax.annotate(f"blew up after {p['blew_up_after_s']:.0f} s",
                            (p["cost_s_per_s"], BLOWN_UP_ROW), textcoords="offset points",
                            xytext=(-6, -12), ha="right", fontsize=7, color=colour)
                continue
            ax.scatter(p["cost_s_per_s"], p["tracking_error"], color=colour, marker=marker,
                       s=50, zorder=3, label=label)
            if p.get("jammed"):
                ax.scatter(p["cost_s_per_s"], p["tracking_error"], facecolors="none",
                           edgecolors="black", marker="o", s=220, zorder=4,
                           label="jammed: delivered < 0.9 of the explicit DEM's mass")
                ax.annotate(f"jammed: {p['discharged_kg'] / 1e3:.0f} t of "
                            f"{p['explicit_discharged_kg'] / 1e3:.0f} t",
                            (p["cost_s_per_s"], p["tracking_error"]),
                            textcoords="offset points", xytext=(-10, 10), ha="right",
                            fontsize=7)
            if p.get("creeping"):
                ax.scatter(p["cost_s_per_s"], p["tracking_error"], facecolors="none",
                           edgecolors="tab:red", marker="s", s=160, zorder=4,
                           label=f"creeping: the bulk beyond {BULK_DISTANCE:g} m of the feeder "
                                 f"moves > {CREEP_FACTOR:g}x the explicit DEM's")
            if "spread" in p:
                ax.vlines(p["cost_s_per_s"], p["spread"]["min"], p["spread"]["max"],
                          color=colour, lw=1,
                          label="range: each run against each explicit replica")
        ax.axhline(0.10, color="black", ls=":", lw=1, label="target 0.10")
        floor = next((p["tracking_error"] for p in result["points"][scene]
                      if p["model"] == "dem_explicit" and p["tracking_error"] is not None), None)
        if floor is not None:  # the method comparison's goal: within 0.05 of the floor
            ax.axhline(floor + FLOOR_MARGIN, color="tab:green", ls="--", lw=0.8,
                       label=f"explicit noise floor + {FLOOR_MARGIN:g}")
        ax.axvline(1.0, color="grey", ls="-", lw=0.5, label="real time")
        ax.set_ylim(-0.03, top)
        ax.set_xscale("log")
        ax.set_xlabel("compute per simulated second, one core [s/s]")
        ax.set_title(scene, fontsize=9)
    axes[0, 0].set_ylabel("tracking error against the explicit DEM replicas [-]")
    shown = {}  # every model once, whichever panel drew it
    for ax in axes[0]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            shown.setdefault(label, handle)
    # below the panels: inside one it hides points (the jammed run's, at the right)
    columns = 4 if len(scenes) > 1 else 3  # a one-scene figure is narrower
    fig.legend(shown.values(), shown.keys(), fontsize=7, loc="lower center", ncol=columns,
               frameon=False)
    plotstyle.title(fig, "Paper-scale stockpile: tracking error against compute",
                    f"{window:g} s windows; DEM: CPU time, storage models: "
                    "wall time on one core")
    fig.tight_layout(rect=(0.0, 0.04 * -(-len(shown) // columns), 1.0, 1.0))
    plotstyle.save(fig, path, dpi=120)


def _outcome(folder: Path, run: str) -> dict:
    with np.load(folder / "train" / f"{run}.npz") as stored:
        return {"time": np.asarray(stored["time"], dtype=np.float64),
                "mass": np.asarray(stored["mass"], dtype=np.float64),
                "velocity": np.asarray(stored["velocity"], dtype=np.float64),
                "setpoint": np.asarray(stored["setpoint"], dtype=np.float64),
                "out_time": np.asarray(stored["out_time"], dtype=np.float64),
                "out_mass": np.asarray(stored["out_mass"], dtype=np.float64)}


def _grid(folder: Path) -> dict:
    return json.loads((folder / "manifest.json").read_text())["grid"]


def _record(folder: Path, run: str) -> dict:
    return next(r for r in json.loads((folder / "manifest.json").read_text())["runs"]
                if r["name"] == run)


def _field_map(ax, fig, field, grid: dict, title: str, top: float, cmap: str, unit: str):
    image = ax.imshow(field, origin="lower", cmap=cmap, vmin=0.0, vmax=top, aspect="equal",
                      extent=(grid["x_min"], grid["x_max"], grid["y_min"], grid["y_max"]))
    ax.set_xlim(-40.0, 40.0)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title, fontsize=9)
    fig.colorbar(image, ax=ax, label=unit, shrink=0.8)


def plot_scene(scene: str, row: dict, label: str, method_data: Path, reference: Path,
               path: Path) -> None:
    """Top: the discharged mass over time and the pile at the end (areal mass on the
    ROM grid) of explicit replica 0 and of the method. Bottom: the speed of the bulk
    beyond ``BULK_DISTANCE`` of the feeder over time, and the cells' speed at the end:
    where a jam or a creep shows."""
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    runs = [("explicit DEM, replica " + name.rsplit("_r", 1)[1], _outcome(reference, name),
             bulk_speed(reference, _record(reference, name)))
            for name in row["explicit_replicas"]]
    several = len(row["method_runs"]) > 1
    methods = [(label + (", run " + name.rsplit("_r", 1)[1] if several else ""),
                _outcome(method_data, name), bulk_speed(method_data, _record(method_data, name)))
               for name in row["method_runs"]]
    ours = methods[0]  # the pile maps show the first run
    fig, axes = plt.subplots(2, 3, figsize=(17, 9.0),
                             gridspec_kw={"width_ratios": [1.0, 1.4, 1.4]})
    for k, (name, run, bulk) in enumerate([*runs, *methods]):
        t0 = run["time"][0]
        order = np.argsort(run["out_time"], kind="stable")
        taken = run["out_time"][order] - t0
        style = (dict(color="tab:purple", lw=2 if run is ours[1] else 1, alpha=(
            1.0 if run is ours[1] else 0.6), ls="-" if run is ours[1] else "--")
            if k >= len(runs) else dict(color="tab:green", lw=1, alpha=0.4 + 0.2 * k))
        axes[0, 0].step(np.concatenate([[0.0], taken]),
                        np.concatenate([[0.0], np.cumsum(run["out_mass"][order])]) / 1e3,
                        where="post", label=name, **style)
        axes[1, 0].plot(run["time"] - t0, bulk, label=name, **style)
    t = np.linspace(0.0, row["simulated_s"], 50)
    axes[0, 0].plot(t, ours[1]["setpoint"].mean() * t / 1e3, color="black", ls=":", lw=1,
                    label=f"set point, {ours[1]['setpoint'].mean() / 1e3:.2f} t/s")
    axes[0, 0].set_xlabel("time since the scene's start [s]")
    axes[0, 0].set_ylabel("discharged mass [t]")
    axes[0, 0].set_title("feeder output", fontsize=9)
    plotstyle.legend(axes[0, 0], fontsize=7)
    axes[1, 0].set_yscale("log")
    axes[1, 0].set_xlabel("time since the scene's start [s]")
    axes[1, 0].set_ylabel("mean speed [m/s]")
    axes[1, 0].set_title(f"bulk beyond {BULK_DISTANCE:g} m of the feeder's centre", fontsize=9)
    plotstyle.legend(axes[1, 0], fontsize=7)
    grid = _grid(reference)
    cell_area = ((grid["x_max"] - grid["x_min"]) / grid["nx"]
                 * (grid["y_max"] - grid["y_min"]) / grid["ny"])
    ends = [runs[0][:2], ours[:2]]
    top = max(float(run["mass"][-1].max()) for _, run in ends) / cell_area
    speeds = [np.ma.masked_where(run["mass"][-1] <= 0.0,
                                 np.hypot(run["velocity"][-1, ..., 0], run["velocity"][-1, ..., 1]))
              for _, run in ends]
    fastest = max(float(np.percentile(speed.compressed(), 99)) for speed in speeds)
    for column, ((name, run), speed) in enumerate(zip(ends, speeds), start=1):
        when = f"at the end ({run['time'][-1] - run['time'][0]:.0f} s)"
        _field_map(axes[0, column], fig, run["mass"][-1] / cell_area, grid, f"{name}\n{when}",
                   top, "viridis", "areal mass [kg/m^2]")
        _field_map(axes[1, column], fig, speed, grid, f"{name}:\nspeed {when}", fastest,
                   "magma", "speed [m/s]")
    verdict = (f"jammed: delivered {row['discharged_kg'] / 1e3:.0f} t of the explicit "
               f"DEM's {row['explicit_discharged_kg'] / 1e3:.0f} t, nothing after "
               f"{row['last_discharge_s']:.0f} s" if row["jammed"] else
               f"delivered {row['discharged_kg'] / 1e3:.0f} t, the explicit DEM "
               f"{row['explicit_discharged_kg'] / 1e3:.0f} t")
    if row["creeping"]:
        verdict += (f"; creeping: the bulk beyond {BULK_DISTANCE:g} m of the feeder moves at "
                    f"{row['bulk_speed_m_s']:.3f} m/s, the explicit DEM's at "
                    f"{min(row['explicit_bulk_speed_m_s']):.4f}-"
                    f"{max(row['explicit_bulk_speed_m_s']):.4f} m/s")
    plotstyle.title(fig, f"{scene}: {label} against the explicit DEM", verdict)
    fig.tight_layout()
    plotstyle.save(fig, path, dpi=110)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--method-data", type=Path, required=True, action="append",
                        help="exported design of another DEM method run on the reference's "
                             "scenes (paper_heldout_nonsmooth); repeat it for several settings")
    parser.add_argument("--reference", type=Path, default=REFERENCE,
                        help="exported explicit held-out design (default: the shipped one)")
    parser.add_argument("--evaluation", type=Path, default=EVALUATION,
                        help="`minetwin rom evaluate` summary of the shipped ROM on it")
    parser.add_argument("--window", type=float, default=WINDOW_S,
                        help="tracking-error window [s] (default 30; 5 for the 20 s rock scene)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    try:
        runs = [score_dem_method(folder, args.reference, window=args.window)
                for folder in args.method_data]
        evaluation = json.loads(args.evaluation.read_text())
    except (ValidationError, OSError) as error:
        print(f"paper_scale_methods: error: {error}", file=sys.stderr)
        return 2
    result = {"methods": runs, "points": points(evaluation, runs),
              "evaluation": str(args.evaluation)}
    args.out.mkdir(parents=True, exist_ok=True)
    jsonio.write(args.out / "paper_scale_methods.json", result, indent=1)
    plot(result, args.out / "paper_scale_methods.png", args.window)
    for folder, methods in zip(args.method_data, runs):
        label = label_of(methods)
        for scene, row in methods["scenes"].items():
            plot_scene(scene, row, label, folder, args.reference,
                       args.out / f"scene_{scene}_{slug_of(methods)}.png")
            each = " / ".join(f"{r['tracking_error']:.3f}" for r in row["realisations"])
            print(f"{scene}: {label}: tracking error {row['tracking_error']:.3f} "
                  f"({row['tracking_error_spread']['min']:.3f}-"
                  f"{row['tracking_error_spread']['max']:.3f} over "
                  f"{len(row['realisations'])} run(s) x {len(row['explicit_replicas'])} "
                  f"explicit replicas; run by run {each}), explicit noise "
                  f"floor {row['tracking_error_dem_noise_floor']:.3f}; CPU s per simulated s: "
                  f"{row['method_cost']['cpu_s_per_simulated_s']:.1f} against the explicit "
                  f"DEM's {methods['explicit_costs'][scene]['cpu_s_per_simulated_s']:.1f}; "
                  f"discharged {row['discharged_kg'] / 1e3:.0f} t against the explicit "
                  f"DEM's {row['explicit_discharged_kg'] / 1e3:.0f} t"
                  + (f" (jammed: nothing left after {row['last_discharge_s']:.0f} s)"
                     if row["jammed"] else "")
                  + f"; bulk beyond {BULK_DISTANCE:g} m of the feeder at "
                    f"{row['bulk_speed_m_s']:.4f} m/s, the explicit DEM's "
                    f"{min(row['explicit_bulk_speed_m_s']):.4f}-"
                    f"{max(row['explicit_bulk_speed_m_s']):.4f}"
                  + (" (creeping)" if row["creeping"] else ""))
        for scene, row in methods["failed"].items():
            print(f"{scene}: {label}: blew up after {row['after_s']:.1f} s ({row['reason']}); "
                  f"picture at the failure: {row['picture']}")
        for scene, why in methods["skipped"].items():
            print(f"{scene}: {label}: not scored: {why}", file=sys.stderr)
    print(f"wrote {args.out / 'paper_scale_methods.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
