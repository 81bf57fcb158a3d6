"""The paper's step-response experiments (section "Results", "Step response").

Two runs of ``examples/step_response.toml``: the hardness step at the left
source (1 -> 2, reached by the truck at 350 s) and the reference run with
hardness 1 at both sources. From their time series:

* crusher: mean power over four truck cycles before the truck reaches the
  harder ore and over four cycles starting 60 s after ("about 60 s later ...
  the crusher power draw has increased by 40 %, from 1.5 kW to 2.1 kW"), their
  ratio, the delay until the power's 30 s average exceeds 1.25 x the
  before-level, the mass-weighted zone hardness after the step (paper: about 1.4)
  and the dominant period of the power signal after the step from its
  autocorrelation (paper: 55 s, the truck cycle);
* mill: the time after the discharge start (500 s) when the mill hardness
  first exceeds ``RISE_THRESHOLD`` (paper: about 90 s), the mean hardness
  from then on (paper: about 1.5) and the mill power of the step run over
  the reference run's while harder ore is in the mill (paper: about +20 %).

Figures in the spirit of the paper's "crusherStep" and "millStepBest":
signal, 30 s moving average, mass in the asset and the hardness seen by a
virtual sensor.
"""

from __future__ import annotations

import copy
import sqlite3
from pathlib import Path

import numpy as np

from cosim import jsonio

SCENARIO = Path(__file__).resolve().parents[2] / "examples" / "step_response.toml"
RISE_THRESHOLD = 1.05
"""Mill hardness [-] that counts as "harder ore has arrived" (reference: 1)."""
WINDOW_CYCLES = 4
"""Truck cycles in each crusher averaging window."""
CRUSHER_DELAY_S = 60.0
"""Start of the after-window after the truck reaches the harder ore [s] (paper: ~60 s)."""
QUICK_UNTIL_S = 800.0
"""Simulated time of ``--quick`` runs [s] (the full run uses the scenario's 1200 s)."""

DESCRIPTION = ("the paper's hardness step at the left source and the reference run: crusher "
               "power ratio, truck period, mill hardness rise and mill power vs reference")


def reference_config(config: dict) -> dict:
    """The same scenario with hardness 1 at every source (the paper's reference run)."""
    from cosim.scenario import assets_of_kind

    reference = copy.deepcopy(config)
    for name in assets_of_kind(reference, "source"):
        reference["assets"][name]["hardness"] = {"kind": "constant", "value": 1.0}
    return reference


def hard_ore_reached_s(events_path, load_time: float) -> float:
    """Start of the first loading of ore harder than 1 [s], from the event store."""
    with sqlite3.connect(events_path) as db:
        row = db.execute(
            "SELECT MIN(e.time) FROM events e JOIN event_particles p ON e.event_id = p.event_id "
            "WHERE e.type = 'appear' AND p.hardness > 1.0 + 1e-9").fetchone()
    return float("nan") if row[0] is None else float(row[0]) - load_time


def dominant_period(t: np.ndarray, signal: np.ndarray, low: float = 10.0,
                    high: float = 150.0) -> float:
    """Lag [s] of the highest autocorrelation peak in [low, high] (biased estimator)."""
    dt = float(np.median(np.diff(t)))
    x = np.nan_to_num(signal - np.nanmean(signal))
    n = x.size
    spectrum = np.fft.rfft(x, 2 * n)
    acf = np.fft.irfft(spectrum * np.conj(spectrum))[:n] / n
    lags = np.arange(n) * dt
    inside = np.flatnonzero((lags >= low) & (lags <= high))
    if inside.size < 3:
        return float("nan")
    k = inside[1:-1]
    peaks = k[(acf[k] >= acf[k - 1]) & (acf[k] >= acf[k + 1])]
    if peaks.size == 0:
        return float("nan")
    return float(lags[peaks[np.argmax(acf[peaks])]])


def _window(series, start: float, end: float):
    index = series.index.to_numpy()
    return series[(index > start) & (index <= end)]


def analyse(step, reference, config: dict, hard_s: float, cycle_s: float) -> dict:
    """Step-response figures from the two runs' time series."""
    before = _window(step, hard_s - WINDOW_CYCLES * cycle_s, hard_s)
    after_start = hard_s + CRUSHER_DELAY_S
    after = _window(step, after_start, after_start + WINDOW_CYCLES * cycle_s)
    power_before = float(before["crusher_fmu.power"].mean())
    power_after = float(after["crusher_fmu.power"].mean())
    zone_mass = after["crusher.zone_mass_kg"].to_numpy()
    zone_hardness = np.nan_to_num(after["crusher.zone_hardness"].to_numpy())
    settled = _window(step, after_start, step.index[-1])
    period = dominant_period(settled.index.to_numpy(), settled["crusher_fmu.power"].to_numpy())

    dt = float(np.median(np.diff(step.index.to_numpy())))
    average = _moving_average(step["crusher_fmu.power"].to_numpy(),
                              int(round(config["simulation"]["sensor_window_s"] / dt)))
    risen_power = step.index[(step.index > hard_s) & (average > 1.25 * power_before)]
    pile = config["assets"]["stockpile"]
    schedule = next(iter(pile["outlets"].values()))["discharge"]
    discharge_s = next((t for t, rate in schedule if rate > 0), float("nan"))
    mill = _window(step, discharge_s, step.index[-1])
    risen = mill.index[mill["mill.hardness"].to_numpy() >= RISE_THRESHOLD]
    rise_s = float(risen[0] - discharge_s) if len(risen) else float("nan")
    harder = mill["mill.hardness"].to_numpy() >= RISE_THRESHOLD
    times = mill.index[harder]
    ref_power = reference["mill_fmu.power"].reindex(times)
    step_power = mill["mill_fmu.power"][harder]
    return {
        "hard_ore_reached_s": hard_s,
        "truck_cycle_nominal_s": cycle_s,
        "crusher_power_before_w": power_before,
        "crusher_power_after_w": power_after,
        "crusher_power_ratio": power_after / power_before if power_before > 0 else float("nan"),
        "crusher_hardness_mean_after": float((zone_mass * zone_hardness).sum() / zone_mass.sum())
        if zone_mass.sum() > 0 else float("nan"),
        "truck_cycle_period_s": period,
        "crusher_power_rise_delay_s": float(risen_power[0] - hard_s) if len(risen_power)
        else float("nan"),
        "discharge_start_s": float(discharge_s),
        "mill_hardness_rise_time_s": rise_s,
        "mill_hardness_mean_after": float(mill["mill.hardness"][harder].mean())
        if harder.any() else float("nan"),
        "mill_power_ratio_vs_reference": float(step_power.mean() / ref_power.mean())
        if harder.any() else float("nan"),
        "mill_mass_ratio_vs_reference": float(
            mill["mill.mass_kg"][harder].mean()
            / reference["mill.mass_kg"].reindex(times).mean()) if harder.any() else float("nan"),
        "mass_balance_rel_error": float(max(step["plant.mass_balance_rel_error"].max(),
                                            reference["plant.mass_balance_rel_error"].max())),
    }


def checks(summary: dict) -> list[str]:
    """The mechanism the paper shows; a list of what does not hold (empty: all hold).

    A figure that could not be computed (None or NaN) fails its check.
    """
    summary = {key: float("nan") if value is None else value for key, value in summary.items()}
    failed = []
    if not 1.25 <= summary["crusher_power_ratio"] <= 1.55:
        failed.append(f"crusher_power_ratio {summary['crusher_power_ratio']:.3f} "
                      "not in [1.25, 1.55]")
    if not abs(summary["truck_cycle_period_s"] - summary["truck_cycle_nominal_s"]) <= 5.0:
        failed.append(f"truck_cycle_period_s {summary['truck_cycle_period_s']:.1f} not within "
                      f"5 s of {summary['truck_cycle_nominal_s']:.1f}")
    if not summary["mill_power_ratio_vs_reference"] > 1.0:
        failed.append(f"mill_power_ratio_vs_reference {summary['mill_power_ratio_vs_reference']}"
                      " not > 1")
    if not summary["mass_balance_rel_error"] < 1e-9:
        failed.append(f"mass_balance_rel_error {summary['mass_balance_rel_error']:.2e} >= 1e-9")
    return failed


def _moving_average(values, samples: int):
    import pandas as pd

    return pd.Series(values).rolling(max(samples, 1), min_periods=1).mean().to_numpy()


def plot(step, reference, summary: dict, out: Path, window_s: float = 30.0,
         run: str | None = None) -> list[Path]:
    """crusher_step.png and mill_step.png (paper figures "crusherStep", "millStepBest").

    ``run`` names the run in the titles (``cosim.plotstyle.run_label``).
    """
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    dt = float(np.median(np.diff(step.index.to_numpy())))
    n = int(round(window_s / dt))
    t = step.index.to_numpy()
    avg = f"{window_s:g} s moving average"
    paths = []

    fig, (ax_p, ax_h) = plt.subplots(2, 1, figsize=(9, 7.5), sharex=True)
    power = step["crusher_fmu.power"].to_numpy() / 1e3
    ax_p.plot(t, power, lw=0.6, color="tab:blue", label="crusher power")
    ax_p.plot(t, _moving_average(power, n), lw=1.8, color="navy", label=f"crusher power, {avg}")
    ax_p.set_ylabel("(a) crusher power [kW]")
    mass = ax_p.twinx()
    mass.grid(False)
    # behind the power traces: the charge explains the power, it is not the result
    mass.set_zorder(ax_p.get_zorder() - 1)
    ax_p.patch.set_visible(False)
    mass.plot(t, step["crusher.zone_mass_kg"].to_numpy(), lw=0.6, color="tab:gray", alpha=0.6,
              label="mass in crusher zone (right axis)")
    mass.set_ylabel("mass in crusher zone [kg]", color="tab:gray")
    ax_h.plot(t, step["crusher.zone_hardness"].to_numpy(), lw=0.6, color="tab:green",
              label="zone hardness (virtual sensor)")
    ax_h.plot(t, step["crusher.zone_hardness_avg"].to_numpy(), lw=1.8, color="darkgreen",
              label=f"zone hardness, {avg}")
    ax_h.set_ylabel("(b) crusher zone hardness [-]")
    ax_h.set_xlabel("time [s]")
    hard = f"hard ore reaches the crusher ({summary['hard_ore_reached_s']:.0f} s)"
    for ax in (ax_p, ax_h):
        plotstyle.mark(ax, summary["hard_ore_reached_s"], hard)
    plotstyle.legend(ax_p, mass, loc="upper left")
    plotstyle.legend(ax_h, loc="upper left")
    plotstyle.title(fig, f"Crusher step response: {summary['crusher_power_before_w'] / 1e3:.2f}"
                    f" -> {summary['crusher_power_after_w'] / 1e3:.2f} kW "
                    f"(x{summary['crusher_power_ratio']:.2f}), truck-cycle period "
                    f"{summary['truck_cycle_period_s']:.0f} s", run)
    fig.tight_layout()
    paths.append(plotstyle.save(fig, out / "crusher_step.png"))

    fig, (ax_p, ax_h) = plt.subplots(2, 1, figsize=(9, 7.5), sharex=True)
    for series, label, color in ((step, "hardness step run", "tab:red"),
                                 (reference, "reference run (hardness 1)", "tab:blue")):
        rt = series.index.to_numpy()
        p = series["mill_fmu.power"].to_numpy() / 1e6
        ax_p.plot(rt, p, lw=0.5, color=color, alpha=0.5, label=f"mill power, {label}")
        ax_p.plot(rt, _moving_average(p, n), lw=1.8, color=color,
                  label=f"mill power, {label}, {avg}")
        ax_h.plot(rt, series["mill.hardness"].to_numpy(), lw=0.5, color=color, alpha=0.5,
                  label=f"mill hardness, {label}")
        ax_h.plot(rt, series["mill.hardness_avg"].to_numpy(), lw=1.8, color=color,
                  label=f"mill hardness, {label}, {avg}")
    mass = ax_p.twinx()
    mass.grid(False)
    mass.plot(t, step["mill.mass_kg"].to_numpy() / 1e3, lw=1.0, color="tab:orange", ls=":",
              label="ore mass in mill, hardness step run (right axis)")
    mass.plot(reference.index.to_numpy(), reference["mill.mass_kg"].to_numpy() / 1e3, lw=1.0,
              color="tab:cyan", ls=":", label="ore mass in mill, reference run (right axis)")
    mass.set_ylabel("ore mass in mill [t]")
    ax_p.set_ylabel("(a) mill power [MW]")
    ax_h.set_ylabel("(b) mill hardness [-]")
    ax_h.set_xlabel("time [s]")
    start = f"stockpile discharge starts ({summary['discharge_start_s']:.0f} s)"
    for ax in (ax_p, ax_h):
        plotstyle.mark(ax, summary["discharge_start_s"], start)
    plotstyle.legend(ax_p, mass, loc="upper left", fontsize=7)
    plotstyle.legend(ax_h, loc="upper left", fontsize=7)
    plotstyle.title(fig, f"Mill step response: hardness rises "
                    f"{summary['mill_hardness_rise_time_s']:.0f} s after the discharge starts; "
                    f"power x{summary['mill_power_ratio_vs_reference']:.2f} vs the reference run",
                    run)
    fig.tight_layout()
    paths.append(plotstyle.save(fig, out / "mill_step.png"))
    return paths


def reproduce(out_dir, *, quick: bool = False, progress: bool = True,
              scenario=SCENARIO, storage_model: str | None = None) -> tuple[dict, list[str]]:
    """Run both experiments into ``out_dir``; returns (summary, failed checks)."""
    from cosim.scenario import load, run_scenario

    out = Path(out_dir)
    config = load(scenario)
    until = QUICK_UNTIL_S if quick else config["simulation"]["until_s"]
    name = Path(scenario).stem
    step_sim, step_summary = run_scenario(config, out / "step", until=until,
                                          storage_model=storage_model,
                                          progress=progress and "step response: hardness step run",
                                          scenario_name=name)
    ref_sim, ref_summary = run_scenario(reference_config(step_sim.config), out / "reference",
                                        until=until, storage_model=storage_model,
                                        progress=progress and "step response: reference run",
                                        scenario_name=f"{name} (reference)")
    truck = next(a for a in step_sim.assets.values() if hasattr(a, "cycle_time"))
    hard_s = hard_ore_reached_s(out / "step" / "events.sqlite",
                                step_sim.config["assets"]["trucks"]["trucks"][0]["load_time_s"])
    summary = analyse(step_sim.timeseries, ref_sim.timeseries, step_sim.config, hard_s,
                      truck.cycle_time)
    summary.update(quick=quick, simulated_s=until,
                   storage_model=step_sim.config["assets"]["stockpile"]["model"],
                   wall_s=step_summary["wall_s"] + ref_summary["wall_s"])
    from cosim.plotstyle import run_label

    plot(step_sim.timeseries, ref_sim.timeseries, summary, out,
         step_sim.config["simulation"]["sensor_window_s"],
         run=run_label(step_sim.config, scenario=name))
    failed = checks(summary)
    summary["checks_failed"] = failed
    summary = {key: None if isinstance(value, float) and not np.isfinite(value) else value
               for key, value in summary.items()}       # strict JSON: no NaN
    jsonio.write(out / "summary.json", summary, indent=2, sort_keys=True)
    return summary, failed
