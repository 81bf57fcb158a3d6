"""One plotting style for every MineTwin figure.

Every figure the project writes (``cosim.analyses``, ``cosim.scenario``'s
overview, the reference overlays, ``surrogate.dem.plots``, ``examples/``)
goes through here, so that each one is

- titled with what it shows and, for a simulation, the run: scenario, seed
  and storage model (``run_label``, ``title``);
- drawn with a unit on every axis label (``[kW]``, ``[-]`` for dimensionless);
- explained by a legend entry for every line, twin axes included
  (``legend`` merges the handles of an axis and its twins; ``mark`` draws a
  labelled vertical line for an event such as a step or a start);
- not exaggerating a flat signal (``span_at_least``);
- written by ``save``, which first calls each of ``SAVE_HOOKS`` with the
  figure, so that a test reads the figure's artists (``problems``) instead
  of the PNG.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

RC = {"figure.dpi": 100, "axes.grid": True, "grid.alpha": 0.3, "axes.titlesize": 10,
      "figure.titlesize": 11, "legend.fontsize": 8, "legend.framealpha": 0.85,
      "axes.labelsize": 9}
"""The project's matplotlib settings."""

SAVE_HOOKS: list = []
"""Callables ``hook(figure, path)`` run by ``save`` before the figure is written."""


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend with the project's settings."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update(RC)
    return plt


def run_label(config: dict | None = None, *, scenario: str | None = None, seed=None,
              model: str | None = None) -> str:
    """``scenario NAME, seed S, storage model M`` from a scenario config
    (``cosim.scenario.validate``'s keys) and/or explicit values."""
    if config is not None:
        seed = config.get("simulation", {}).get("seed") if seed is None else seed
        if model is None:
            models = [table.get("model") for table in config.get("assets", {}).values()
                      if isinstance(table, dict) and table.get("kind") == "stockpile"]
            model = " + ".join(dict.fromkeys(models)) or None
    parts = [f"scenario {scenario or 'unnamed'}"]
    if seed is not None:
        parts.append(f"seed {seed}")
    if model is not None:
        parts.append(f"storage model {model}")
    return ", ".join(parts)


SIGNAL_UNITS = (("rate_kg_s", "kg/s"), ("_kg", "kg"), ("_m", "m"), ("_s", "s"), ("power", "W"),
                ("torque", "N m"), ("hardness", "-"), ("grade", "-"), ("d_mean", "m"),
                ("d80", "m"), ("mass", "kg"), ("speed", "m/s"), ("bwi", "kWh/t"))
"""Unit of a recorded signal by the end of its name (SI, as the time series hold them)."""


def signal_unit(name: str) -> str:
    """The SI unit of a time-series signal such as ``mill_fmu.power`` (``W``);
    ``SI`` when its name does not say."""
    leaf = name.rsplit(".", 1)[-1].lower()
    for ending, unit in SIGNAL_UNITS:
        if leaf.endswith(ending) or (ending.isalpha() and ending in leaf):
            return unit
    return "SI"


def title(fig, what: str, run: str | None = None) -> None:
    """The figure's title: what it shows, and on a second line the run."""
    fig.suptitle(what if run is None else f"{what}\n{run}")


def legend(ax, *twins, **options):
    """One legend on ``ax`` for the lines of ``ax`` and its ``twins``."""
    handles, labels = [], []
    for axis in (ax, *twins):
        h, l = axis.get_legend_handles_labels()
        handles += h
        labels += l
    options.setdefault("loc", "best")
    return ax.legend(handles, labels, **options)


def mark(ax, x: float, label: str, **style):
    """A dashed vertical line at ``x`` with its own legend entry ``label``."""
    style = {"color": "k", "ls": "--", "lw": 0.8, **style}
    return ax.axvline(x, label=label, **style)


def span_at_least(ax, values, min_span: float, axis: str = "y") -> None:
    """Limits around ``values`` at least ``min_span`` wide (in data units), so
    that a nearly flat signal is drawn flat instead of filling the axis."""
    finite = np.asarray(values, dtype=np.float64)
    finite = finite[np.isfinite(finite)]
    if not finite.size:
        return
    low, high = float(finite.min()), float(finite.max())
    half = max(high - low, min_span) * 0.55
    middle = 0.5 * (low + high)
    (ax.set_ylim if axis == "y" else ax.set_xlim)(middle - half, middle + half)


def save(fig, path, dpi: int = 110, **options) -> Path:
    """Run ``SAVE_HOOKS``, write ``fig`` as PNG at ``path``, close it; returns the path."""
    path = Path(path)
    for hook in SAVE_HOOKS:
        hook(fig, path)
    fig.savefig(path, dpi=dpi, **options)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def _has_unit(label: str) -> bool:
    return "[" in label and "]" in label.split("[", 1)[1]


def _flatten(container):
    for part in container:
        if isinstance(part, (tuple, list)):
            yield from _flatten(part)
        elif part is not None:
            yield part


def problems(fig) -> list[str]:
    """What a figure lacks: a title, a unit on an axis label, a legend entry
    for a line. Empty when the figure follows the style."""
    fig.canvas.draw()  # tick labels exist once drawn: an axis without them needs no label
    found = []
    titles = [fig._suptitle.get_text() if fig._suptitle else ""]
    titles += [ax.get_title() for ax in fig.axes]
    if not any(text.strip() for text in titles):
        found.append("no title")
    legend_texts = set()
    for legend_ in [*fig.legends, *(ax.get_legend() for ax in fig.axes)]:
        if legend_ is not None:
            legend_texts.update(text.get_text() for text in legend_.get_texts())
    for number, ax in enumerate(fig.axes):
        if not ax.axison:
            continue
        name = ax.get_title() or f"axes {number}"
        colorbar = getattr(ax, "_colorbar", None)
        drawn = ax.lines or ax.collections or ax.patches or ax.images
        if colorbar is not None:
            label = ax.get_ylabel() or ax.get_xlabel()
            if not _has_unit(label):
                found.append(f"{name}: colour bar label {label!r} has no [unit]")
            continue
        if not drawn:
            continue
        for which, label, ticks in (("x", ax.get_xlabel(), ax.xaxis.get_ticklabels()),
                                    ("y", ax.get_ylabel(), ax.yaxis.get_ticklabels())):
            shown = any(tick.get_visible() and tick.get_text() for tick in ticks) or label
            axis_visible = (ax.xaxis if which == "x" else ax.yaxis).get_visible()
            if axis_visible and shown and not _has_unit(label):
                found.append(f"{name}: {which} label {label!r} has no [unit]")
        # the caps and bars of an error bar belong to its container's legend entry
        explained = {id(part) for container in ax.containers
                     if container.get_label() in legend_texts
                     for part in _flatten(container)}
        for line in ax.lines:
            label = line.get_label()
            if id(line) in explained:
                continue
            if label.startswith("_") or label not in legend_texts:
                found.append(f"{name}: line {label!r} is in no legend")
    return found
