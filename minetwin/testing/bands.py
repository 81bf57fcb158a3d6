"""Tolerance bands around a reference signal (FMI cross-check style).

Source: the FMI cross-check rules and the Reference FMUs, which judge a
simulation result against a reference CSV by a band ("tube") drawn around
the reference curve: a vertical width (tolerance on the value) and a
horizontal width (a time shift the result may have). A result passes if
every sample lies inside the band.

Our band, at a result sample time ``t``:

    window  W(t) = [t - s, t + s] clipped to the reference's time span
    lower   = min over W of y_ref - allowance(t)
    upper   = max over W of y_ref + allowance(t)
    allowance(t) = atol + rtol * max over W of |y_ref|

with ``s`` the allowed time shift [s], ``atol`` the absolute tolerance in the
signal's own unit and ``rtol`` the relative tolerance [-] (as numpy's
``isclose``: relative to the reference's magnitude). The reference is linear
between its samples, so the window's extremes are taken over the reference
samples inside the window and the interpolated values at its two ends.
With ``s = 0``, ``atol = rtol = 0`` the band is the reference itself.

NaN in a reference marks an undefined sample (a sensor over an empty asset):
where no defined reference lies in the window, the result must be NaN too;
where the window holds both, a NaN result is accepted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosim.errors import ValidationError

MAX_LISTED = 3
"""How many failing times a message lists before summarising."""


@dataclass(frozen=True)
class Tolerance:
    """How far a result may lie from its reference.

    Parameters
    ----------
    atol : float
        Absolute tolerance in the signal's unit (default 0).
    rtol : float
        Relative tolerance [-], fraction of the reference's magnitude
        (default 0.01).
    time_shift : float
        Time shift [s] the result may have against the reference (default 0).
    """

    atol: float = 0.0
    rtol: float = 0.01
    time_shift: float = 0.0

    def __post_init__(self):
        for name in ("atol", "rtol", "time_shift"):
            value = getattr(self, name)
            if (isinstance(value, bool) or not isinstance(value, (int, float, np.floating))
                    or not np.isfinite(value) or value < 0):
                raise ValidationError(name, "a finite number >= 0", f"got {value!r}")

    def describe(self) -> str:
        return f"atol={self.atol:g}, rtol={self.rtol:g}, time shift ±{self.time_shift:g} s"


@dataclass
class SignalComparison:
    """Result of comparing one signal with its reference.

    Arrays are over the result's samples inside the reference's time span.
    """

    name: str
    tolerance: Tolerance
    time: np.ndarray
    value: np.ndarray
    reference: np.ndarray
    """The reference interpolated at ``time``."""
    lower: np.ndarray
    upper: np.ndarray
    coverage_problem: str = ""
    outside: np.ndarray | None = None
    """Samples outside the band (default: value not within [lower, upper])."""

    def __post_init__(self):
        if self.outside is None:
            with np.errstate(invalid="ignore"):
                self.outside = ~((self.value >= self.lower) & (self.value <= self.upper))

    @property
    def passed(self) -> bool:
        return not self.coverage_problem and not self.outside.any()

    @property
    def n_outside(self) -> int:
        return int(self.outside.sum())

    @property
    def deviation(self) -> np.ndarray:
        """Result minus reference at the same time, in the signal's unit."""
        return self.value - self.reference

    @property
    def excess(self) -> np.ndarray:
        """How far each sample lies outside the band (0 inside; inf where outside
        because the value or the band is undefined)."""
        with np.errstate(invalid="ignore"):
            beyond = np.fmax(np.fmax(self.value - self.upper, self.lower - self.value), 0.0)
        return np.where(self.outside, np.where(np.isfinite(beyond) & (beyond > 0), beyond,
                                               np.inf), 0.0)

    @property
    def worst_index(self) -> int | None:
        """Sample with the largest excess over the band, else the largest deviation."""
        if self.time.size == 0:
            return None
        if self.outside.any():
            return int(np.argmax(self.excess))
        magnitude = np.abs(self.deviation)
        if np.isnan(magnitude).all():
            return 0
        return int(np.nanargmax(magnitude))

    @property
    def worst_deviation(self) -> float:
        i = self.worst_index
        return float("nan") if i is None else float(self.deviation[i])

    @property
    def worst_time(self) -> float:
        i = self.worst_index
        return float("nan") if i is None else float(self.time[i])

    def allowed_at(self, i: int) -> tuple[float, float]:
        """The band ``(lower, upper)`` at sample ``i``."""
        return float(self.lower[i]), float(self.upper[i])

    def message(self) -> str:
        """One paragraph a person can act on."""
        head = f"signal {self.name!r}"
        if self.coverage_problem:
            return f"{head}: {self.coverage_problem}"
        if self.passed:
            return (f"{head} stays inside its band ({self.tolerance.describe()}); worst "
                    f"deviation {self.worst_deviation:+.6g} at t = {self.worst_time:g} s")
        i = self.worst_index
        lo, hi = self.allowed_at(i)
        first = np.flatnonzero(self.outside)
        times = ", ".join(f"{t:g}" for t in self.time[first[:MAX_LISTED]])
        more = f" and {first.size - MAX_LISTED} more" if first.size > MAX_LISTED else ""
        return (f"{head} leaves its tolerance band ({self.tolerance.describe()}) at "
                f"{first.size} of {self.time.size} samples (t = {times}{more} s). Worst at "
                f"t = {self.time[i]:g} s: value {self.value[i]:.6g}, reference "
                f"{self.reference[i]:.6g} (deviation {self.deviation[i]:+.6g}), allowed "
                f"[{lo:.6g}, {hi:.6g}]. If the change is intended, record a new reference; "
                f"if not, the model or its inputs changed behaviour there.")


def _range_extremes(values: np.ndarray, start: np.ndarray, stop: np.ndarray):
    """Min and max of ``values[start[k]:stop[k]]`` for every k (sparse table, O(n log n)).

    Empty ranges give +inf / -inf.
    """
    lows, highs = [values], [values]
    width = 1
    while 2 * width <= values.size:
        lows.append(np.minimum(lows[-1][:-width], lows[-1][width:]))
        highs.append(np.maximum(highs[-1][:-width], highs[-1][width:]))
        width *= 2
    length = stop - start
    low = np.full(start.shape, np.inf)
    high = np.full(start.shape, -np.inf)
    nonempty = length > 0
    level = np.zeros(start.shape, dtype=np.int64)
    level[nonempty] = np.floor(np.log2(length[nonempty])).astype(np.int64)
    for j in np.unique(level[nonempty]):
        pick = nonempty & (level == j)
        a, b = start[pick], stop[pick] - (1 << int(j))
        low[pick] = np.minimum(lows[j][a], lows[j][b])
        high[pick] = np.maximum(highs[j][a], highs[j][b])
    return low, high


def _as_series(name: str, what: str, time, values) -> tuple[np.ndarray, np.ndarray]:
    time = np.asarray(time, dtype=np.float64).ravel()
    values = np.asarray(values, dtype=np.float64).ravel()
    if time.size != values.size:
        raise ValidationError(f"{what} of {name!r}", "as many values as time points",
                              f"{values.size} values, {time.size} times")
    if time.size == 0:
        raise ValidationError(f"{what} of {name!r}", "at least one sample", "got none")
    if not np.isfinite(time).all() or np.any(np.diff(time) < 0):
        raise ValidationError(f"{what} time of {name!r}", "finite and non-decreasing [s]")
    return time, values


def compare_signal(name: str, time, values, ref_time, ref_values,
                   tolerance: Tolerance = Tolerance()) -> SignalComparison:
    """Compare a result ``values(time)`` with a reference ``ref_values(ref_time)``.

    The result must cover the reference's time span (to within the allowed
    time shift and half a result sample); samples outside that span are not
    judged. NaN in the result is always outside the band.
    """
    t, y = _as_series(name, "result", time, values)
    tr, yr = _as_series(name, "reference", ref_time, ref_values)
    if np.isinf(yr).any():
        raise ValidationError(f"reference of {name!r}", "finite values or NaN (undefined)",
                              f"{int(np.isinf(yr).sum())} infinite")
    slack = tolerance.time_shift + (0.5 * float(np.median(np.diff(t))) if t.size > 1 else 0.0)
    problem = ""
    if t[0] > tr[0] + slack or t[-1] < tr[-1] - slack:
        problem = (f"result covers t = {t[0]:g}..{t[-1]:g} s but the reference covers "
                   f"{tr[0]:g}..{tr[-1]:g} s; run the scenario at least as long as the "
                   f"reference (--until {tr[-1]:g})")
    inside = (t >= tr[0]) & (t <= tr[-1])
    t, y = t[inside], y[inside]
    s = tolerance.time_shift
    lo_t = np.clip(t - s, tr[0], tr[-1])
    hi_t = np.clip(t + s, tr[0], tr[-1])
    edge_lo, edge_hi = np.interp(lo_t, tr, yr), np.interp(hi_t, tr, yr)
    start = np.searchsorted(tr, lo_t, side="left")
    stop = np.searchsorted(tr, hi_t, side="right")
    undefined = np.isnan(yr)
    inner_min, _ = _range_extremes(np.where(undefined, np.inf, yr), start, stop)
    _, inner_max = _range_extremes(np.where(undefined, -np.inf, yr), start, stop)
    window_min = np.fmin(np.fmin(edge_lo, edge_hi), inner_min)
    window_max = np.fmax(np.fmax(edge_lo, edge_hi), inner_max)
    with np.errstate(invalid="ignore"):  # all-NaN windows give inf - inf
        allowance = tolerance.atol + tolerance.rtol * np.maximum(np.abs(window_min),
                                                                 np.abs(window_max))
        lower, upper = window_min - allowance, window_max + allowance
    # NaN marks an undefined sample (e.g. a sensor over an empty asset): where the
    # window holds no defined reference the result must be undefined too; where it
    # holds some, an undefined result is accepted if the window also holds NaN
    nan_count = np.concatenate(([0], np.cumsum(undefined)))
    window_has_nan = ((nan_count[stop] - nan_count[start]) > 0) | np.isnan(edge_lo) \
        | np.isnan(edge_hi)
    defined = np.isfinite(lower) & np.isfinite(upper)
    with np.errstate(invalid="ignore"):
        inside = np.where(np.isnan(y), ~defined | window_has_nan,
                          defined & (y >= lower) & (y <= upper))
    return SignalComparison(name=name, tolerance=tolerance, time=t, value=y,
                            reference=np.interp(t, tr, yr),
                            lower=np.where(defined, lower, np.nan),
                            upper=np.where(defined, upper, np.nan), coverage_problem=problem,
                            outside=~inside)
