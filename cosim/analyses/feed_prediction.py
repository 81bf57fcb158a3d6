"""Properties of the mill feed predicted from the storage model, and what really left.

Source: paper section "Predicting the properties of the mill feed": with
particle tracking the properties of the stored ore are known in time and
space (eq. observation); given a storage flow model, the particles that
will leave within a horizon (30 s in the paper) are known in advance, so the
feed that will reach the mill is predicted before it leaves the storage.

The prediction for (t, t + H] is the mass-weighted mean of each property
over the particles the storage model expects to leave,

    p_pred(t) = sum_n w_n p_n / sum_n w_n,   (ids, w) = storage.predict(H, q_out)

with w_n [kg] the mass of particle n expected to leave. Any model of
``cosim.storage`` (FIFO, perfect mixing, the ROM) provides ``predict``.
The realised feed is the mass-weighted mean over the storage's exit events
in (t, t + H]. The storage averages are mass-weighted means over the
particles held, from the storage's enter/exit events.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from cosim import jsonio
from cosim.analyses.tracking import occupancy_sum, residence_intervals, windowed_sums
from cosim.errors import ValidationError
from cosim.master import Component

PROPERTIES = ("grade", "hardness")
"""Particle properties the feed prediction reports (mass-weighted means)."""


def predicted_feed(storage, horizon: float, discharge_rate: float,
                   properties=PROPERTIES) -> dict[str, float]:
    """Mass [kg] and mass-weighted ``properties`` of the feed of the next ``horizon`` [s].

    ``storage`` is a bound ``cosim.storage.StorageModel``; NaN properties
    when nothing is expected to leave.
    """
    if not (np.isfinite(horizon) and horizon > 0):
        raise ValidationError("horizon", "finite and > 0 s", f"got {horizon!r}")
    ids, weights = storage.predict(horizon, discharge_rate)
    total = float(np.sum(weights))
    out = {"mass": total}
    slots = storage.particles.slots(ids)
    for name in properties:
        values = storage.particles.attribute(name)[slots]
        out[name] = float(weights @ values / total) if total > 0 else float("nan")
    return out


class FeedPredictionProbe(Component):
    """Master component that records the storage model's predicted feed every step.

    Parameters
    ----------
    storage : cosim.storage.StorageModel
        The stockpile's bound storage model.
    discharge_rate : callable
        ``discharge_rate(t)`` -> current feeder rate [kg/s].
    horizon : float
        Prediction horizon H [s] (paper: 30 s).
    name : str
        Component name (time-series columns ``<name>.grade`` ...).

    Outputs ``mass`` [kg] and the mass-weighted ``grade``, ``hardness`` of
    the feed predicted for (t, t + H], sampled at the end of each step.
    """

    def __init__(self, storage, discharge_rate, *, horizon: float = 30.0,
                 name: str = "feed_prediction"):
        super().__init__()
        self.name = name
        self.storage = storage
        self.discharge_rate = discharge_rate
        self.horizon = float(horizon)
        self._last = {"mass": 0.0, **{p: float("nan") for p in PROPERTIES}}

    def step(self, t: float, dt: float) -> None:
        self._last = predicted_feed(self.storage, self.horizon,
                                    float(self.discharge_rate(t + dt)))

    def outputs(self) -> dict[str, float]:
        return dict(self._last)


def realised_feed(exits: pd.DataFrame, times, horizon: float,
                  properties=PROPERTIES) -> pd.DataFrame:
    """Mass and mass-weighted properties of what left in (t, t + horizon] for each t.

    ``exits`` are the storage's exit-event particle rows (``time``, ``mass``
    and the properties); an exit stamped t has left by t, so a prediction
    made at t is about the exits stamped in (t, t + horizon].
    """
    times = np.asarray(times, dtype=np.float64)
    t = exits["time"].to_numpy(dtype=np.float64)
    mass = exits["mass"].to_numpy(dtype=np.float64)
    columns = [mass] + [mass * exits[p].to_numpy(dtype=np.float64) for p in properties]
    sums = windowed_sums(t, np.column_stack(columns), times + horizon, horizon)
    frame = pd.DataFrame({"time": times, "mass": sums[:, 0]})
    with np.errstate(invalid="ignore", divide="ignore"):
        for j, p in enumerate(properties):
            frame[p] = np.where(sums[:, 0] > 0, sums[:, j + 1] / sums[:, 0], np.nan)
    return frame


def outflow_moving_average(exits: pd.DataFrame, times, window: float = 2.0,
                           properties=PROPERTIES) -> pd.DataFrame:
    """Mass-weighted properties of the outflow in the trailing ``window`` [s] (paper: 2 s)."""
    times = np.asarray(times, dtype=np.float64)
    mass = exits["mass"].to_numpy(dtype=np.float64)
    columns = [mass] + [mass * exits[p].to_numpy(dtype=np.float64) for p in properties]
    sums = windowed_sums(exits["time"].to_numpy(dtype=np.float64), np.column_stack(columns),
                         times, window)
    frame = pd.DataFrame({"time": times, "rate_kg_s": sums[:, 0] / window})
    with np.errstate(invalid="ignore", divide="ignore"):
        for j, p in enumerate(properties):
            frame[p] = np.where(sums[:, 0] > 0, sums[:, j + 1] / sums[:, 0], np.nan)
    return frame


def storage_averages(particles: pd.DataFrame, asset: str, times,
                     properties=PROPERTIES) -> pd.DataFrame:
    """Mass [kg] held in ``asset`` and its mass-weighted properties over time (from events)."""
    stays = residence_intervals(particles, asset, leave_types=("exit",))
    mass = stays["mass"].to_numpy()
    columns = [mass] + [mass * stays[p].to_numpy() for p in properties]
    sums = occupancy_sum(stays["t_in"].to_numpy(), stays["t_out"].to_numpy(),
                         np.column_stack(columns), times)
    frame = pd.DataFrame({"time": np.asarray(times, dtype=np.float64), "mass": sums[:, 0]})
    with np.errstate(invalid="ignore", divide="ignore"):
        for j, p in enumerate(properties):
            frame[p] = np.where(sums[:, 0] > 0, sums[:, j + 1] / sums[:, 0], np.nan)
    return frame


def prediction_errors(predicted: pd.DataFrame, realised: pd.DataFrame,
                      properties=PROPERTIES, min_mass: float = 0.0) -> dict[str, float]:
    """Mean absolute error of each predicted property against the realised feed.

    Rows are matched on ``time``; rows where either side is NaN or the
    realised mass is at most ``min_mass`` [kg] are left out.
    """
    joined = predicted.merge(realised, on="time", suffixes=("_pred", "_real"))
    ok = joined["mass_real"] > min_mass
    errors = {}
    for p in properties:
        diff = (joined[f"{p}_pred"] - joined[f"{p}_real"])[ok].dropna()
        errors[p] = float(diff.abs().mean()) if len(diff) else float("nan")
    return errors



class PileSnapshot(Component):
    """Master component that keeps the stockpile's particles at one time (paper figure
    pileDistribution): position [m], velocity [m/s], grade, hardness, mass [kg] and the
    expected time to leave [s] (cumulative mass ahead in the model's order of leaving
    divided by the feeder rate)."""

    name = "pile_snapshot"

    def __init__(self, stockpile, at: float):
        super().__init__()
        self.stockpile = stockpile
        self.at = float(at)
        self.frame: pd.DataFrame | None = None

    def step(self, t: float, dt: float) -> None:
        if self.frame is not None or t + dt < self.at - 1e-9:
            return
        store = self.stockpile.particles
        order = self.stockpile.model.held_ids()
        slots = store.slots(order)
        mass = store.mass[slots]
        rate = max(float(self.stockpile.scheduled_rate(t + dt)), 1e-9)
        self.frame = pd.DataFrame({
            "x": store.position[slots, 0], "y": store.position[slots, 1],
            "speed": np.linalg.norm(store.velocity[slots], axis=1),
            "grade": store.grade[slots], "hardness": store.hardness[slots], "mass": mass,
            "time_to_leave_s": (np.cumsum(mass) - mass) / rate})
        self.frame.attrs["time"] = t + dt


# ------------------------------------------------------------------ reproduce
DESCRIPTION = ("mill-feed prediction: pile distributions, storage averages and the feed "
               "predicted for the next 30 s against what leaves, per storage model")
HORIZON_S = 30.0
"""Prediction horizon [s] (paper: 30 s)."""
OUTFLOW_WINDOW_S = 2.0
"""Moving-average window of the realised outflow [s] (paper: 2 s)."""
QUICK_UNTIL_S = 450.0
FULL_UNTIL_S = 1500.0
ROM_MODEL_ENV = "MINETWIN_ROM_MODEL"
"""Environment variable naming a trained ROM file (``minetwin rom train``) to compare
instead of the ROM's own default model (the shipped paper-scale one)."""


def storage_models() -> tuple[list[tuple[str, dict]], dict]:
    """(name, options) of the storage models to compare, and the ones skipped with why:
    FIFO, perfect mixing and, where the "rom" storage model is registered, the ROM (the
    paper's funnel-zone prediction) with its default model or the file ``ROM_MODEL_ENV``
    names."""
    from cosim.storage import registered_models

    models, skipped = [("fifo", {}), ("mixing", {})], {}
    if "rom" not in registered_models():
        skipped["rom"] = "no storage model named rom is registered"
        return models, skipped
    path = rom_model_from_env()
    models.append(("rom", {"model": path} if path else {}))
    return models, skipped


def rom_model_from_env() -> str | None:
    """The ROM file ``ROM_MODEL_ENV`` names (None when unset or empty), refused by name
    when it is no file."""
    import os

    path = os.environ.get(ROM_MODEL_ENV) or None
    if path is not None and not Path(path).is_file():
        raise ValidationError(ROM_MODEL_ENV, "the path of a ROM model file (minetwin rom train)",
                              f"got {path!r}, which is no file")
    return path


def analyse_model(run, predicted: pd.DataFrame, min_mass: float) -> tuple[dict, dict]:
    """Errors and curves of one storage model's run."""
    table = run.particles
    exits = table[(table["asset"] == "stockpile") & (table["type"] == "exit")]
    times = run.times
    realised = realised_feed(exits, times, HORIZON_S)
    errors = prediction_errors(predicted, realised, min_mass=min_mass)
    return errors, {"realised": realised, "predicted": predicted,
                    "outflow": outflow_moving_average(exits, times, OUTFLOW_WINDOW_S),
                    "averages": storage_averages(table, "stockpile", times)}


def plot(curves: dict, snapshots: dict, out, run: str | None = None) -> list:
    """Figures in the spirit of the paper's pileDistribution and storageEvolutionandOutflow;
    one row per storage model, ``run`` names the scenario and seed in the titles."""
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    out = Path(out)
    # grade in % like the monitor and every other figure; the data are fractions [-]
    units = {"speed": "speed [m/s]", "grade": "grade [%]", "hardness": "hardness [-]"}
    shown = {"speed": 1.0, "grade": 100.0, "hardness": 1.0}
    paths = []
    names = list(curves)
    fig, axes = plt.subplots(len(names), 3, figsize=(12, 3.2 * len(names)), squeeze=False)
    for row, name in zip(axes, names):
        snap = snapshots[name]
        spatial = snap is not None and len(snap) and np.ptp(snap["x"]) + np.ptp(snap["y"]) > 0
        for ax, column in zip(row, ("speed", "grade", "hardness")):
            if snap is None or not len(snap):
                ax.set_axis_off()
                continue
            if spatial:
                points = ax.scatter(snap["x"], snap["y"], c=snap[column] * shown[column], s=4,
                                    cmap="viridis")
                ax.set_xlabel("x [m]")
                ax.set_ylabel("y [m]")
                ax.set_aspect("equal")
                fig.colorbar(points, ax=ax, label=units[column])
                ax.set_title(f"{name}: {column} at t = {snap.attrs['time']:.0f} s", fontsize=9)
                continue
            # no geometry: the pile in the model's order of leaving, the next
            # horizon's feed (the analogue of the funnel zone) shaded
            ax.axvspan(0.0, HORIZON_S, color="0.9", label=f"feed of the next {HORIZON_S:g} s")
            if column == "speed":
                ax.hist(snap["time_to_leave_s"], bins=40, weights=snap["mass"] * 1e-3)
                ax.set_ylabel("held mass [t]")
                title = "mass by time to leave"
            else:
                ax.scatter(snap["time_to_leave_s"], snap[column] * shown[column], s=4)
                ax.set_ylabel(units[column])
                title = column
            ax.set_xlabel("expected time to leave [s]")
            ax.set_title(f"{name}: {title} at t = {snap.attrs['time']:.0f} s\n"
                         f"(grey: the feed of the next {HORIZON_S:g} s)", fontsize=9)
            ax.grid(False)
    plotstyle.title(fig, "Pile distribution per storage model", run)
    fig.tight_layout()
    paths.append(plotstyle.save(fig, out / "pile_distribution.png", dpi=100))

    fig, axes = plt.subplots(len(names), 2, figsize=(12, 3.2 * len(names)), squeeze=False)
    for (left, right), name in zip(axes, names):
        c = curves[name]
        averages = c["averages"]
        left.plot(averages["time"], averages["grade"] * 100, label="grade")
        twin = left.twinx()
        twin.plot(averages["time"], averages["hardness"], color="tab:orange",
                  label="hardness (right axis)")
        left.set_title(f"{name}: storage averages (mass-weighted)", fontsize=9)
        left.set_xlabel("time [s]")
        left.set_ylabel("grade [%]")
        twin.set_ylabel("hardness [-]")
        plotstyle.legend(left, twin, fontsize=8)
        out_ma, pred, real = c["outflow"], c["predicted"], c["realised"]
        right.plot(out_ma["time"], out_ma["grade"] * 100, color="tab:orange", lw=0.8,
                   label=f"outflow grade ({OUTFLOW_WINDOW_S:g} s moving average)")
        right.plot(pred["time"], pred["grade"] * 100, color="tab:blue", lw=1.0,
                   label=f"predicted grade of the next {HORIZON_S:g} s")
        right.plot(real["time"], real["grade"] * 100, color="k", lw=0.8, ls="--",
                   label=f"realised grade of the next {HORIZON_S:g} s")
        right.set_title(f"{name}: feed prediction", fontsize=9)
        right.set_xlabel("time [s]")
        right.set_ylabel("grade [%]")
        right.legend(fontsize=7)
    plotstyle.title(fig, "Storage evolution and outflow per storage model", run)
    fig.tight_layout()
    paths.append(plotstyle.save(fig, out / "storage_evolution_and_outflow.png", dpi=100))
    return paths


def reproduce(out_dir, *, quick: bool = False, progress: bool = True, seed: int | None = None):
    """One run per storage model with the prediction probe; (summary, failed checks)."""
    import json

    from cosim.analyses.profile_run import output_folder, run_profile, scenario_config

    out = output_folder(out_dir)
    until = QUICK_UNTIL_S if quick else FULL_UNTIL_S
    config = scenario_config(quick=quick)
    models, skipped = storage_models()
    summary = {"quick": quick, "simulated_s": until, "horizon_s": HORIZON_S,
               "outflow_window_s": OUTFLOW_WINDOW_S, "storage_models": [m for m, _ in models],
               "storage_models_skipped": skipped, "feed_grade_prediction_mae": {},
               "feed_hardness_prediction_mae": {}, "wall_s": {}}
    curves, snapshots = {}, {}
    for name, options in models:
        model_config = json.loads(json.dumps(config))
        model_config["assets"]["stockpile"]["model"] = name
        model_config["assets"]["stockpile"]["options"] = options
        probes = []

        def feed_probe(simulation):
            pile = simulation.assets["stockpile"]
            return FeedPredictionProbe(pile.model, pile.scheduled_rate, horizon=HORIZON_S)

        def snapshot_probe(simulation):
            probes.append(PileSnapshot(simulation.assets["stockpile"], at=0.8 * until))
            return probes[-1]

        run = run_profile(out / f"run_{name}", until=until, config=model_config, seed=seed,
                          progress=progress and f"feed prediction: {name} run",
                          probes=(feed_probe, snapshot_probe))
        ts = run.timeseries
        predicted = pd.DataFrame({"time": run.times,
                                  **{key: ts[f"feed_prediction.{key}"].to_numpy()
                                     for key in ("mass", *PROPERTIES)}})
        rates = [rate for outlet in model_config["assets"]["stockpile"]["outlets"].values()
                 for _, rate in outlet["discharge"] if rate > 0]
        # compare where a full horizon of feed is realised (feeder running, pile not empty)
        min_mass = 0.9 * HORIZON_S * (min(rates) if rates else 0.0)
        errors, curves[name] = analyse_model(run, predicted, min_mass)
        snapshots[name] = probes[0].frame if probes else None
        summary["feed_grade_prediction_mae"][name] = errors["grade"]
        summary["feed_hardness_prediction_mae"][name] = errors["hardness"]
        summary["wall_s"][name] = run.run_summary["wall_s"]
        summary["seed"] = run.config["simulation"]["seed"]
    from cosim.analyses.profile_run import SCENARIO
    from cosim.plotstyle import run_label

    label = run_label(scenario=Path(SCENARIO).stem, seed=summary.get("seed"),
                      model=", ".join(curves))
    summary["figures"] = [p.name for p in plot(curves, snapshots, out, label)]
    failed = [f"{name}: no prediction could be compared" for name in curves
              if not np.isfinite(summary["feed_grade_prediction_mae"][name])]
    summary["checks_failed"] = failed
    jsonio.write(out / "summary.json", summary, indent=2, sort_keys=True)
    return summary, failed
