"""Reference results: record a scenario's signals, compare a rerun against them.

As the FMI Reference FMUs ship one reference CSV per FMU, a MineTwin
scenario names the signals that define its behaviour and a reference CSV
holds them: a ``time`` column [s] followed by one column per signal, values
written with 17 significant digits (exact round trip). A rerun passes if
every signal lies inside its tolerance band (``minetwin.testing.bands``).

The scenario TOML names the signals and tolerances in a ``[reference]``
table (every key optional except ``signals``)::

    [reference]
    signals = ["crusher.power", "mill.power"]
    until = 600.0        # s, default run length for `minetwin reference record`
    rtol = 0.02          # -, relative to the reference's magnitude
    atol = 0.0           # in each signal's unit
    time_shift = 1.0     # s

    [reference.tolerance."crusher.power"]   # per-signal overrides
    atol = 50.0
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cosim.errors import ValidationError
from cosim.plotstyle import signal_unit
from minetwin.testing.bands import SignalComparison, Tolerance, compare_signal
from cosim.tomlfile import read_toml

TIME_COLUMN = "time"


@dataclass
class ReferenceSpec:
    """What a scenario's ``[reference]`` table says: signals, run length, tolerances."""

    signals: list[str]
    until: float | None = None
    default: Tolerance = field(default_factory=Tolerance)
    per_signal: dict[str, Tolerance] = field(default_factory=dict)

    def tolerance(self, signal: str) -> Tolerance:
        return self.per_signal.get(signal, self.default)

    @classmethod
    def from_scenario(cls, path) -> "ReferenceSpec":
        """Read the ``[reference]`` table of scenario TOML ``path``."""
        path = Path(path)
        document = read_toml(path, "scenario")
        return cls.from_table(document.get("reference"), origin=str(path))

    @classmethod
    def from_table(cls, table, origin: str = "scenario") -> "ReferenceSpec":
        if not isinstance(table, dict):
            raise ValidationError("reference", "a [reference] table naming the signals",
                                  f"{origin} has none")
        signals = table.get("signals")
        if (not isinstance(signals, list) or not signals
                or not all(isinstance(s, str) for s in signals)):
            raise ValidationError("reference.signals", "a non-empty list of signal names",
                                  f"{origin}: got {signals!r}")
        known = {"signals", "until", "atol", "rtol", "time_shift", "tolerance"}
        unknown = sorted(set(table) - known)
        if unknown:
            raise ValidationError("reference", f"keys among {sorted(known)}",
                                  f"{origin}: unknown {unknown}")
        default = _tolerance(table, Tolerance(), "reference")
        per_signal = {}
        for signal, override in (table.get("tolerance") or {}).items():
            if signal not in signals:
                raise ValidationError(f"reference.tolerance.{signal}",
                                      f"a signal listed in reference.signals {signals}")
            per_signal[signal] = _tolerance(override, default, f"reference.tolerance.{signal}")
        until = table.get("until")
        if until is not None and not (isinstance(until, (int, float)) and until > 0):
            raise ValidationError("reference.until", "a number > 0 s", f"got {until!r}")
        return cls(signals=list(signals), until=None if until is None else float(until),
                   default=default, per_signal=per_signal)


def _tolerance(table: dict, base: Tolerance, where: str) -> Tolerance:
    values = {}
    for key in ("atol", "rtol", "time_shift"):
        value = table.get(key, getattr(base, key))
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValidationError(f"{where}.{key}", "a number >= 0", f"got {value!r}")
        values[key] = float(value)
    try:
        return Tolerance(**values)
    except ValidationError as exc:
        raise ValidationError(f"{where}.{exc.field}", exc.allowed, str(exc)) from None


@dataclass
class ReferenceResult:
    """A reference: time [s] and signal columns, with the file it came from."""

    time: np.ndarray
    signals: dict[str, np.ndarray]
    source: str = "(in memory)"

    @classmethod
    def from_timeseries(cls, timeseries, signals) -> "ReferenceResult":
        """Take ``signals`` from a time series indexed by time [s]."""
        from minetwin.testing.assertions import signal_from

        columns = {}
        for name in signals:
            _, columns[name] = signal_from(timeseries, name)
        return cls(time=np.asarray(timeseries.index, dtype=np.float64), signals=columns)

    def write(self, path) -> Path:
        """Write the CSV (``time`` first, 17 significant digits)."""
        import pandas as pd

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        frame = pd.DataFrame({TIME_COLUMN: self.time, **self.signals})
        frame.to_csv(path, index=False, float_format="%.17g")
        self.source = str(path)
        return path

    @classmethod
    def read(cls, path) -> "ReferenceResult":
        import pandas as pd

        path = Path(path)
        if not path.is_file():
            raise ValidationError("reference", "an existing reference CSV", f"{path} not found")
        frame = pd.read_csv(path)
        if frame.columns.empty or frame.columns[0] != TIME_COLUMN:
            raise ValidationError("reference", f"a CSV whose first column is {TIME_COLUMN!r}",
                                  f"{path} starts with {list(frame.columns[:1])}")
        if len(frame.columns) < 2:
            raise ValidationError("reference", "at least one signal column", f"{path} has none")
        time = frame[TIME_COLUMN].to_numpy(dtype=np.float64)
        signals = {name: frame[name].to_numpy(dtype=np.float64) for name in frame.columns[1:]}
        return cls(time=time, signals=signals, source=str(path))


@dataclass
class ComparisonReport:
    """Per-signal comparisons of a run against a reference."""

    comparisons: list[SignalComparison]
    reference: str = ""

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.comparisons)

    @property
    def failed(self) -> list[SignalComparison]:
        return [c for c in self.comparisons if not c.passed]

    def rows(self) -> list[dict]:
        rows = []
        for c in self.comparisons:
            i = c.worst_index
            lo, hi = c.allowed_at(i) if i is not None else (float("nan"), float("nan"))
            rows.append({
                "signal": c.name,
                "unit": signal_unit(c.name),
                "worst deviation": c.worst_deviation,
                "at t [s]": f"{c.worst_time:g}",
                "value": float(c.value[i]) if i is not None else float("nan"),
                "reference": float(c.reference[i]) if i is not None else float("nan"),
                "band there": f"[{lo:.6g}, {hi:.6g}]",
                "outside": f"{c.n_outside}/{c.time.size}",
                "result": "pass" if c.passed else "FAIL",
            })
        return rows

    def table(self) -> str:
        """A fixed-width table: one line per signal, its worst deviation and verdict."""
        headers = ["signal", "unit", "worst deviation", "at t [s]", "value", "reference",
                   "band there", "outside", "result"]
        cells = [[_cell(row[h]) for h in headers] for row in self.rows()]
        widths = [max(len(h), *(len(r[j]) for r in cells)) for j, h in enumerate(headers)]
        line = "  ".join(h.ljust(w) for h, w in zip(headers, widths)).rstrip()
        rule = "  ".join("-" * w for w in widths)
        body = ["  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip() for r in cells]
        verdict = ("all signals inside their bands" if self.passed else
                   f"{len(self.failed)} of {len(self.comparisons)} signal(s) outside their band")
        return "\n".join([line, rule, *body, verdict])

    def details(self) -> str:
        return "\n".join(c.message() for c in self.failed)

    def plot_failures(self, directory, run: str | None = None) -> list[Path]:
        """Write ``<signal>.png`` overlays (reference, band, result) of failing
        signals; ``run`` names the run in their titles."""
        return [plot_comparison(c, Path(directory), run) for c in self.failed]


def _cell(value) -> str:
    if isinstance(value, float):
        return f"{value:+.6g}" if value == value else "-"
    return str(value)


def compare(timeseries, reference: ReferenceResult, *, signals=None, tolerances=None,
            default: Tolerance | None = None) -> ComparisonReport:
    """Compare ``timeseries`` (indexed by time [s]) with ``reference``.

    ``signals`` defaults to every signal of the reference; ``tolerances``
    maps a signal to its ``Tolerance`` (else ``default``, else 1 % relative).
    A signal missing from the run fails with a message naming it.
    """
    from minetwin.testing.assertions import signal_from

    names = list(signals) if signals is not None else list(reference.signals)
    tolerances = tolerances or {}
    default = default or Tolerance()
    comparisons = []
    for name in names:
        if name not in reference.signals:
            raise ValidationError("signal", f"one of the reference's {list(reference.signals)}",
                                  f"{name!r} is not in {reference.source}")
        tolerance = tolerances.get(name, default)
        if name not in timeseries.columns:
            empty = np.empty(0)
            comparisons.append(SignalComparison(
                name=name, tolerance=tolerance, time=empty, value=empty, reference=empty,
                lower=empty, upper=empty,
                coverage_problem="missing from the run's time series (renamed or removed "
                                 "output?)"))
            continue
        time, values = signal_from(timeseries, name)
        comparisons.append(compare_signal(name, time, values, reference.time,
                                          reference.signals[name], tolerance))
    return ComparisonReport(comparisons=comparisons, reference=reference.source)


def plot_comparison(comparison: SignalComparison, directory: Path,
                    run: str | None = None) -> Path:
    """PNG overlay of one signal: reference, tolerance band, result, samples outside."""
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    directory.mkdir(parents=True, exist_ok=True)
    safe = "".join(ch if ch.isalnum() or ch in "._-" else "_" for ch in comparison.name)
    path = directory / f"{safe}.png"
    c = comparison
    unit = signal_unit(c.name)
    fig, ax = plt.subplots(figsize=(9, 5))
    if c.time.size:
        ax.fill_between(c.time, c.lower, c.upper, color="tab:green", alpha=0.25,
                        label=f"tolerance band ({c.tolerance.describe()})")
        ax.plot(c.time, c.reference, color="tab:green", lw=1.2, label="reference")
        ax.plot(c.time, c.value, color="tab:blue", lw=1.0, label="this run")
        if c.outside.any():
            ax.plot(c.time[c.outside], c.value[c.outside], "x", color="tab:red", ms=4,
                    label=f"outside band ({c.n_outside} samples)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"{c.name} [{unit}]")
    # below the axes, so that it never covers the band
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=4)
    plotstyle.title(fig, f"{c.name}: {'pass' if c.passed else 'FAIL'} against the reference"
                    + (f" ({c.coverage_problem})" if c.coverage_problem else ""), run)
    fig.tight_layout()
    return plotstyle.save(fig, path, dpi=100)
