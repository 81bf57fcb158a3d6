"""The largest communication step within a coupling tolerance, by step doubling.

The master passes signals between components once per communication step H and
holds them in between (zero-order hold, ``cosim.master``), so every signal that
crosses a component carries a coupling error that shrinks with H: first order
for a zero-order hold (Kübler and Schiehlen 2000, "Two methods of simulator
coupling", Math. Comput. Model. Dyn. Syst. 6:93; Arnold, Clauß and Schierz 2013,
"Error analysis and error estimates for co-simulation in FMI for model exchange
and co-simulation V2.0", Arch. Mech. Eng. 60:75).

Step doubling (Richardson extrapolation): with runs of the same scene at H and
H/2, a quantity y of order p has ``y_H - y = C H^p``, so its error at H is

    e_H ~ |y_H - y_H/2| / (1 - 2^-p)          (p = 1: twice the difference)

The quantity compared is each declared signal's mean over consecutive windows of
``window_s`` (a power or a hardness averaged as the paper's analyses average it),
relative to the signal's scale (the largest window mean's magnitude in the finest
run): ``e_H = max over windows |m_H - m_H/2| / scale / (1 - 2^-p)``. p = 1 is
used (the largest factor, so the estimate errs on the safe side); the order the
runs show, ``log2(d_H / d_H/2)`` from three steps, is reported beside it. The
chosen step is the largest step H whose estimate, and that of every smaller
step, is within the tolerance for every declared signal; the error against the
finest run checks the estimate.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from cosim import plotstyle
from cosim.errors import ValidationError

ORDER = 1
"""The coupling order p assumed by the estimate (zero-order hold: first order)."""


def window_means(series: pd.DataFrame, signal: str, window_s: float,
                 until: float) -> np.ndarray:
    """Means of ``signal`` over the windows [k w, (k+1) w) up to ``until`` [s]."""
    time = series.index.to_numpy(dtype=np.float64)
    values = series[signal].to_numpy(dtype=np.float64)
    count = int(until // window_s)
    which = np.floor(time / window_s).astype(np.int64)
    keep = (which >= 0) & (which < count) & np.isfinite(values)
    sums = np.bincount(which[keep], weights=values[keep], minlength=count)
    counts = np.bincount(which[keep], minlength=count)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


def signal_scale(finest_means: np.ndarray) -> float:
    """A signal's scale: the largest window mean's magnitude in the finest run
    (1 for a signal that stays at 0, so that its errors are absolute)."""
    scale = float(np.nanmax(np.abs(finest_means))) if np.isfinite(finest_means).any() else 0.0
    return scale if scale > 0 else 1.0


def check_ladder(steps, field: str = "steps") -> list[float]:
    """``steps`` [s] sorted, or a ``ValidationError`` unless they are at least two and
    each the double of the one before (H, 2H, 4H, ...)."""
    steps = sorted(steps)
    if len(steps) < 2:
        raise ValidationError(field, "at least two communication steps", f"got {steps}")
    for a, b in zip(steps, steps[1:]):
        if not math.isclose(b, 2.0 * a, rel_tol=1e-9):
            raise ValidationError(field, "a ladder of doublings (H, 2H, 4H, ...)",
                                  f"got {steps}")
    return steps


def coupling_errors(runs: dict[float, pd.DataFrame], signals: list[str], *,
                    window_s: float, until: float) -> dict:
    """Per step (ascending) and per declared signal: the step-doubling estimate
    ``estimate`` (None for the finest step), the error against the finest run
    ``against_finest`` and the observed order ``order`` (None without three
    steps), all relative to the signal's scale. ``runs``: step [s] -> the run's
    time series at that step."""
    steps = check_ladder(runs)
    if not (math.isfinite(window_s) and window_s >= steps[-1]):
        raise ValidationError("window_s", f">= the largest step {steps[-1]:g} s",
                              f"got {window_s!r}")
    for signal in signals:
        missing = [h for h in steps if signal not in runs[h]]
        if missing:
            raise ValidationError("signals", "signals recorded in the time series",
                                  f"{signal!r} is not recorded")
    means = {h: {s: window_means(runs[h], s, window_s, until) for s in signals} for h in steps}
    finest = steps[0]
    table = {}
    for k, h in enumerate(steps):
        row = {}
        for s in signals:
            scale = signal_scale(means[finest][s])

            def gap(coarse, fine):
                return float(np.nanmax(np.abs(means[coarse][s] - means[fine][s]))) / scale

            estimate = gap(h, steps[k - 1]) / (1.0 - 2.0 ** -ORDER) if k >= 1 else None
            order = None
            if k >= 2:
                coarse, fine = gap(h, steps[k - 1]), gap(steps[k - 1], steps[k - 2])
                order = math.log2(coarse / fine) if coarse > 0 and fine > 0 else None
            row[s] = {"estimate": estimate, "against_finest": gap(h, finest) if k else 0.0,
                      "order": order}
        table[h] = row
    return table


def errors_against(reference: pd.DataFrame, run: pd.DataFrame, signals: list[str], *,
                   window_s: float, until: float) -> dict[str, float]:
    """Per declared signal: the largest difference of ``run``'s window means from
    ``reference``'s, relative to the signal's scale in the reference (as
    ``coupling_errors``' ``against_finest``); for a run at another step scheme (an
    adaptive step) against a fine-step reference."""
    errors = {}
    for signal in signals:
        for frame in (reference, run):
            if signal not in frame:
                raise ValidationError("signals", "signals recorded in the time series",
                                      f"{signal!r} is not recorded")
        fine = window_means(reference, signal, window_s, until)
        scale = signal_scale(fine)
        errors[signal] = float(np.nanmax(np.abs(window_means(run, signal, window_s, until)
                                                - fine))) / scale
    return errors


def largest_step_within(table: dict, tolerance: float) -> float | None:
    """The largest step whose estimate, and every smaller step's, is within
    ``tolerance`` for every signal; None when even the second finest is not."""
    if not (math.isfinite(tolerance) and tolerance > 0):
        raise ValidationError("coupling_tolerance", "> 0 (a fraction of the signal's scale)",
                              f"got {tolerance!r}")
    chosen = None
    for h in sorted(table)[1:]:
        if all(row["estimate"] <= tolerance for row in table[h].values()):
            chosen = h
        else:
            break
    return chosen


def plot(table: dict, costs: dict[float, float], tolerance: float, chosen, path, *,
         run: str | None = None) -> Path:
    """Left: each signal's estimated coupling error (and its error against the
    finest run) against the step, with the tolerance and the chosen step. Right:
    the cost of each step [wall s per simulated s]."""
    plt = plotstyle.pyplot()
    steps = sorted(table)
    signals = list(table[steps[0]])
    fig, (ax, cost_ax) = plt.subplots(1, 2, figsize=(12, 4.8))
    for k, s in enumerate(signals):
        color = f"C{k}"
        ax.plot(steps[1:], [table[h][s]["estimate"] for h in steps[1:]], "o-", color=color,
                label=f"{s}: step-doubling estimate")
        ax.plot(steps[1:], [table[h][s]["against_finest"] for h in steps[1:]], "x--",
                color=color, label=f"{s}: against the {steps[0]:g} s run")
    ax.axhline(tolerance, color="tab:red", ls=":", label=f"tolerance {tolerance:g}")
    if chosen is not None:
        plotstyle.mark(ax, chosen, f"chosen step {chosen:g} s")
    ax.set_xscale("log", base=2)
    ax.set_xticks(steps, [f"{h:g}" for h in steps])
    ax.set_yscale("log")
    ax.set_xlabel("communication step [s]")
    ax.set_ylabel("relative error of the window means [-]")
    ax.set_title("coupling error against the step")
    plotstyle.legend(ax, loc="upper left", fontsize=7)
    cost_ax.plot(steps, [costs[h] for h in steps], "o-", color="k", label="cost of the run")
    if chosen is not None:
        plotstyle.mark(cost_ax, chosen, f"chosen step {chosen:g} s")
    cost_ax.set_xscale("log", base=2)
    cost_ax.set_xticks(steps, [f"{h:g}" for h in steps])
    cost_ax.set_xlabel("communication step [s]")
    cost_ax.set_ylabel("cost [wall s per simulated s]")
    cost_ax.set_title("cost against the step")
    plotstyle.legend(cost_ax, loc="upper right")
    plotstyle.title(fig, "Largest communication step within the coupling tolerance", run)
    fig.tight_layout()
    return plotstyle.save(fig, path)
