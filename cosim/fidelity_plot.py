"""The speed-against-accuracy chart of a fidelity choice, and which model ran when.

Left: every model's card at the scene's operating point (``cosim.fidelity.choose``'s
``compared`` rows): measured tracking error (fraction of the outflow mass, against
the DEM) on x, cost (wall seconds per simulated second, log scale) on y; the DEM's
noise floor, the target (a tracking-error line, or a cost-budget line) and the
chosen model ringed. A model whose card does not hold at the operating point is
drawn hollow. Right (for a run): the ladder rung the stockpile ran on over
simulated time (``NAME.model_rung``, 0 = the cheapest card), with each switch.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from cosim import plotstyle
from cosim.fidelity import REFERENCE_MODEL

MODEL_COLORS = ("tab:green", "tab:olive", "tab:purple", "tab:blue", "tab:brown", "tab:cyan")
"""One colour per ladder rung, cheapest first."""


def plot_fidelity(choice: dict, path, *, series=None, pile: str | None = None,
                  run: str | None = None) -> Path:
    """Write the chart of ``choice`` (``Choice.to_json()``, or a stockpile's
    ``summary.json["fidelity"][NAME]``) to ``path`` (PNG). With the run's time
    series ``series`` and the stockpile's name ``pile``, the right panel shows the
    model that ran over time; ``run`` is the run's label for the title."""
    plt = plotstyle.pyplot()
    timeline = series is not None and pile is not None
    fig, axes = plt.subplots(1, 2 if timeline else 1, figsize=(12 if timeline else 6.5, 4.8),
                             squeeze=False)
    _speed_accuracy(axes[0][0], choice)
    if timeline:
        _timeline(axes[0][1], choice, series, pile)
    point = choice["operating_point"]
    what = (f"Fidelity choice: {choice['model']} at {point['throughput_kg_s']:g} kg/s, "
            f"{point['held_mass_kg'] / 1e3:g} t held, {point['window_s']:g} s window")
    plotstyle.title(fig, what, run)
    fig.tight_layout()
    return plotstyle.save(fig, path)


def _speed_accuracy(ax, choice: dict) -> None:
    for k, row in enumerate(choice["compared"]):
        error, cost = row["tracking_error"], row["wall_s_per_s"]
        if not (math.isfinite(error) and math.isfinite(cost) and cost > 0):
            continue
        holds = row["holds"]
        ax.scatter([error], [cost], s=60, color=MODEL_COLORS[k % len(MODEL_COLORS)],
                   facecolors=MODEL_COLORS[k % len(MODEL_COLORS)] if holds else "none",
                   label=f"{row['model']}" + ("" if holds else " (card does not hold here)"),
                   zorder=3)
    chosen = next(r for r in choice["compared"] if r["model"] == choice["model"])
    ax.scatter([chosen["tracking_error"]], [chosen["wall_s_per_s"]], s=260, facecolors="none",
               edgecolors="k", linewidths=1.5, label=f"chosen: {choice['model']}", zorder=4)
    floor = next((r["noise_floor"] for r in choice["compared"]
                  if r["model"] == REFERENCE_MODEL),
                 chosen["noise_floor"])
    ax.axvline(floor, color="0.4", ls=":", lw=1.0, label=f"DEM noise floor ({floor:.3f})")
    target = choice["target"]
    if "tracking_error" in target:
        ax.axvline(target["tracking_error"], color="tab:red", ls="--", lw=1.0,
                   label=f"target: tracking error <= {target['tracking_error']:g}")
    else:
        ax.axhline(target["wall_s_per_s"], color="tab:red", ls="--", lw=1.0,
                   label=f"budget: {target['wall_s_per_s']:g} wall s per simulated s")
    ax.set_yscale("log")
    ax.set_xlim(0.0, max(1.0, max(r["tracking_error"] for r in choice["compared"]
                                  if math.isfinite(r["tracking_error"])) * 1.05))
    ax.set_xlabel("tracking error against the DEM [-] (fraction of outflow mass)")
    ax.set_ylabel("cost [wall s per simulated s]")
    ax.set_title("every model's card at the operating point")
    plotstyle.legend(ax, loc="upper right")


def _timeline(ax, choice: dict, series, pile: str) -> None:
    rungs = [r["model"] for r in choice["compared"]]
    time = series.index.to_numpy(dtype=np.float64)
    column = f"{pile}.model_rung"
    rung = (series[column].to_numpy(dtype=np.float64) if column in series
            else np.full(time.size, float(rungs.index(choice["model"]))))
    ax.step(time, rung, where="post", color="tab:blue", lw=1.2, label=f"{pile}: model running")
    for k, switch in enumerate(choice.get("switches", [])):
        ax.axvline(switch["time_s"], color="tab:orange", ls="--", lw=0.8,
                   label="switch (from -> to, reason in summary.json)" if k == 0 else None)
    ax.set_yticks(range(len(rungs)), [f"{k}: {m}" for k, m in enumerate(rungs)])
    ax.set_ylim(-0.5, len(rungs) - 0.5)
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("storage model [ladder rung, 0 = cheapest]")
    ax.set_title("which model ran when")
    plotstyle.legend(ax, loc="upper left")
