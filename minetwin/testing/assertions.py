"""Assertions for co-simulation tests, with messages a person can act on.

Each ``assert_*`` raises ``AssertionError`` whose text says what was
expected, what was found, where (time, asset, ids) and what to look at.
Source of the invariants: mass conservation with relative error < 1e-9 and
no tracking id lost or duplicated, the paper's
section "Integration test" (every tracking id entering the stockpile is
held or leaves on the outgoing belt) and section "Results", "Step response"
(gain and delay of a signal after a step in the feed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosim.errors import ValidationError
from minetwin.testing.bands import Tolerance, compare_signal

MAX_LISTED_IDS = 10
"""How many offending ids a message lists."""


def _listing(ids) -> str:
    ids = list(ids)
    text = ", ".join(str(int(i)) for i in ids[:MAX_LISTED_IDS])
    if len(ids) > MAX_LISTED_IDS:
        text += f", ... ({len(ids) - MAX_LISTED_IDS} more)"
    return text


# ------------------------------------------------------------------ mass balance
def assert_mass_balance(source=None, *, mass_in_kg=None, mass_held_kg=None, mass_out_kg=None,
                        time=None, rtol: float = 1e-9, atol: float = 0.0,
                        where: str = "plant") -> float:
    """Mass in = mass held + mass out, within ``atol + rtol * mass in``.

    Parameters
    ----------
    source : mapping or DataFrame, optional
        A run summary / integration report (keys ``mass_in_kg``,
        ``mass_held_kg``, ``mass_out_kg``) or a time series with those
        columns (checked at every row). Keyword values override it.
    mass_in_kg, mass_held_kg, mass_out_kg : float or array [kg]
        The three masses (arrays: one value per recorded time).
    time : array [s], optional
        Times of the array values (used in the message).
    rtol : float
        Relative tolerance [-] (default 1e-9).
    atol : float
        Absolute tolerance [kg] (default 0).
    where : str
        Name of the balanced domain in the message (asset or "plant").

    Returns the worst relative error.
    """
    __tracebackhide__ = True  # pytest shows the message, not these lines
    values = {"mass_in_kg": mass_in_kg, "mass_held_kg": mass_held_kg,
              "mass_out_kg": mass_out_kg}
    for key, value in values.items():
        if value is None:
            if source is None or key not in source:
                raise ValidationError(key, "given, or a key/column of the source",
                                      f"source has {sorted(source) if source is not None else 'nothing'}")
            values[key] = source[key]
    if time is None and hasattr(source, "index") and not isinstance(source, dict):
        time = np.asarray(source.index, dtype=float)
    m_in, held, out = (np.atleast_1d(np.asarray(values[k], dtype=np.float64))
                       for k in ("mass_in_kg", "mass_held_kg", "mass_out_kg"))
    missing = m_in - held - out
    allowed = atol + rtol * np.abs(m_in)
    scale = np.where(np.abs(m_in) > 0, np.abs(m_in), 1.0)
    relative = np.abs(missing) / scale
    bad = ~(np.abs(missing) <= allowed)
    if bad.any():
        i = int(np.argmax(np.where(bad, np.abs(missing), -1.0)))
        at = f" at t = {float(np.atleast_1d(time)[i]):g} s" if time is not None else ""
        first = (f"; first broken at t = {float(np.atleast_1d(time)[np.flatnonzero(bad)[0]]):g} s"
                 if time is not None and bad.sum() > 1 else "")
        verb = "lost" if missing[i] > 0 else "created"
        raise AssertionError(
            f"mass balance of {where} broken{at}: in {m_in[i]:.9g} kg != held {held[i]:.9g} kg "
            f"+ out {out[i]:.9g} kg; {abs(missing[i]):.6g} kg {verb} (relative error "
            f"{relative[i]:.3g} > rtol {rtol:g}, atol {atol:g} kg){first}. Look for an asset "
            f"or exchange that drops or duplicates particles or bins.")
    return float(relative.max())


# ------------------------------------------------------------------ ids
@dataclass
class IdAccount:
    """Where the ids went: lost, duplicated, unknown (never entered), and per-id mass gaps."""

    lost: np.ndarray
    duplicated: np.ndarray
    unknown: np.ndarray
    mass_short: dict
    mass_surplus: dict

    @property
    def ok(self) -> bool:
        return not (self.lost.size or self.duplicated.size or self.unknown.size
                    or self.mass_short or self.mass_surplus)


def account_ids(entered, held=(), left=(), *, entered_mass=None, held_mass=None,
                left_mass=None, split_allowed: bool = False, rtol: float = 1e-9) -> IdAccount:
    """Account for every id that entered: held now or left.

    ``split_allowed`` lets an id appear several times among held and left
    (a tracking id whose mass is spread over several particles or outgoing
    bins); then, if masses are given, each id's held + left mass must equal
    its entered mass to within ``rtol``. Without ``split_allowed`` each id
    that entered must appear exactly once among held and left (particle ids).
    """
    entered = np.asarray(entered, dtype=np.uint64).ravel()
    present = np.concatenate([np.asarray(held, dtype=np.uint64).ravel(),
                              np.asarray(left, dtype=np.uint64).ravel()])
    in_ids, in_counts = np.unique(entered, return_counts=True)
    out_ids, out_counts = np.unique(present, return_counts=True)
    lost = np.setdiff1d(in_ids, out_ids)
    unknown = np.setdiff1d(out_ids, in_ids)
    duplicated = in_ids[in_counts > 1]
    if not split_allowed:
        duplicated = np.union1d(duplicated, out_ids[out_counts > 1])
    short, surplus = {}, {}
    if entered_mass is not None and (held_mass is not None or left_mass is not None):
        present_mass = np.concatenate([
            np.asarray(held_mass if held_mass is not None else np.zeros(np.size(held)),
                       dtype=np.float64).ravel(),
            np.asarray(left_mass if left_mass is not None else np.zeros(np.size(left)),
                       dtype=np.float64).ravel()])
        m_in = np.zeros(in_ids.size)
        np.add.at(m_in, np.searchsorted(in_ids, entered),
                  np.asarray(entered_mass, dtype=np.float64).ravel())
        known = np.isin(present, in_ids)
        m_out = np.zeros(in_ids.size)
        np.add.at(m_out, np.searchsorted(in_ids, present[known]), present_mass[known])
        gap = m_in - m_out
        tol = rtol * np.abs(m_in)
        for i in np.flatnonzero(gap > tol):
            if in_ids[i] not in lost:
                short[int(in_ids[i])] = float(gap[i])
        for i in np.flatnonzero(-gap > tol):
            surplus[int(in_ids[i])] = float(-gap[i])
    return IdAccount(lost=lost, duplicated=duplicated, unknown=unknown,
                     mass_short=short, mass_surplus=surplus)


def assert_ids_accounted(entered, held=(), left=(), *, entered_mass=None, held_mass=None,
                         left_mass=None, split_allowed: bool = False, rtol: float = 1e-9,
                         kind: str = "tracking id", where: str = "the exchange",
                         hint: str = "Follow one of these ids through the event store "
                                     "(minetwin events history DB ID) to see where it went."
                         ) -> IdAccount:
    """No id lost or duplicated: every id that entered is held or has left, once.

    See ``account_ids`` for the parameters. The message lists the offending
    ids (first 10) per kind of fault and ends with ``hint`` (where to look).
    """
    __tracebackhide__ = True  # pytest shows the message, not these lines
    account = account_ids(entered, held, left, entered_mass=entered_mass, held_mass=held_mass,
                          left_mass=left_mass, split_allowed=split_allowed, rtol=rtol)
    if account.ok:
        return account
    problems = []
    if account.lost.size:
        problems.append(f"{account.lost.size} {kind}(s) lost (entered, but neither held nor "
                        f"left): {_listing(account.lost)}")
    if account.duplicated.size:
        problems.append(f"{account.duplicated.size} {kind}(s) duplicated (counted more than "
                        f"once): {_listing(account.duplicated)}")
    if account.unknown.size:
        problems.append(f"{account.unknown.size} {kind}(s) held or left without ever entering: "
                        f"{_listing(account.unknown)}")
    if account.mass_short:
        items = ", ".join(f"{k}: {v:.6g} kg" for k, v in list(account.mass_short.items())[:10])
        problems.append(f"{len(account.mass_short)} {kind}(s) partly lost (mass missing): {items}")
    if account.mass_surplus:
        items = ", ".join(f"{k}: {v:.6g} kg" for k, v in list(account.mass_surplus.items())[:10])
        problems.append(f"{len(account.mass_surplus)} {kind}(s) with more mass out than in "
                        f"(applied twice?): {items}")
    entered_n = np.unique(np.asarray(entered, dtype=np.uint64)).size
    raise AssertionError(f"{where}: of {entered_n} {kind}s that entered, "
                         + "; ".join(problems) + ". " + hint)


# ------------------------------------------------------------------ reference band
def signal_from(frame, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(time, values)`` of column ``name`` of a time series indexed by time [s]."""
    if name not in frame.columns:
        close = [c for c in frame.columns if name.split(".")[-1] in str(c)][:8]
        raise ValidationError("signal", "a column of the time series",
                              f"{name!r} not found; similar: {close or list(frame.columns)[:8]}")
    return np.asarray(frame.index, dtype=np.float64), np.asarray(frame[name], dtype=np.float64)


def assert_signal_within_band(time, values, ref_time, ref_values, *, atol: float = 0.0,
                              rtol: float = 0.01, time_shift: float = 0.0,
                              name: str = "signal"):
    """The signal lies inside the tolerance band of its reference (see ``bands``).

    ``atol`` in the signal's unit, ``rtol`` relative to the reference's
    magnitude, ``time_shift`` [s] the horizontal width of the band.
    Returns the ``SignalComparison``.
    """
    __tracebackhide__ = True  # pytest shows the message, not these lines
    comparison = compare_signal(name, time, values, ref_time, ref_values,
                                Tolerance(atol=atol, rtol=rtol, time_shift=time_shift))
    if not comparison.passed:
        raise AssertionError(comparison.message())
    return comparison


def assert_matches_reference(timeseries, reference, *, signals=None, tolerances=None,
                             plot_dir=None):
    """Every named signal of ``timeseries`` lies inside its band around ``reference``.

    ``reference`` is a reference CSV path or a ``ReferenceResult``;
    ``tolerances`` overrides its per-signal ``Tolerance``s; ``plot_dir``
    receives a PNG overlay of each failing signal. The message is the
    comparison table. Returns the ``ComparisonReport``.
    """
    __tracebackhide__ = True  # pytest shows the message, not these lines
    from minetwin.testing.reference import ReferenceResult, compare

    if not isinstance(reference, ReferenceResult):
        reference = ReferenceResult.read(reference)
    report = compare(timeseries, reference, signals=signals, tolerances=tolerances)
    if plot_dir is not None:
        report.plot_failures(plot_dir)
    if not report.passed:
        raise AssertionError("result differs from the reference " f"{reference.source}:\n"
                             + report.table() + "\n" + report.details())
    return report


# ------------------------------------------------------------------ step response
@dataclass
class StepResponse:
    """Measured response of a signal to a step at ``step_time`` [s].

    ``before`` and ``after`` are the mean levels in their windows, ``gain`` =
    (after - before) / input_change, ``ratio`` = after / before, ``delay`` [s]
    from the step until the smoothed signal first crosses before +
    crossing * (after - before) (inf if it never does).
    """

    step_time: float
    before: float
    after: float
    input_change: float
    gain: float
    ratio: float
    delay: float


def _window_mean(t, y, window, label):
    lo, hi = window
    pick = (t >= lo) & (t < hi)
    if not pick.any():
        raise ValidationError(label, f"a window inside the signal's time span "
                              f"{t[0]:g}..{t[-1]:g} s", f"got [{lo:g}, {hi:g}) s")
    return float(np.mean(y[pick]))


def measure_step_response(time, values, *, step_time: float, before: tuple[float, float],
                          after: tuple[float, float], input_change: float = 1.0,
                          smoothing: float = 0.0, crossing: float = 0.5) -> StepResponse:
    """Gain, ratio and delay of a step response.

    ``smoothing`` [s] is the window of a trailing moving average applied
    before the crossing is looked for (e.g. the truck cycle of 55 s, so the
    oscillation of the feed does not count as a response). Trailing, as the
    virtual sensors' moving average (paper eq. "observation"): a response
    arriving in discrete lumps (truck loads) is seen when the first lump
    arrives, a gradual one with the averaging lag of up to ``smoothing``.
    """
    t = np.asarray(time, dtype=np.float64)
    y = np.asarray(values, dtype=np.float64)
    if not (0 < crossing < 1):
        raise ValidationError("crossing", "in (0, 1)", f"got {crossing!r}")
    if input_change == 0:
        raise ValidationError("input_change", "non-zero", "got 0")
    level_before = _window_mean(t, y, before, "before")
    level_after = _window_mean(t, y, after, "after")
    smooth = y
    if smoothing > 0 and t.size > 1:
        dt = float(np.median(np.diff(t)))
        width = max(int(round(smoothing / dt)), 1)
        kernel = np.ones(width) / width
        padded = np.pad(y, (width - 1, 0), mode="edge")
        smooth = np.convolve(padded, kernel, mode="valid")
    threshold = level_before + crossing * (level_after - level_before)
    rising = level_after >= level_before
    crossed = (smooth >= threshold) if rising else (smooth <= threshold)
    crossed &= t >= step_time
    if level_after == level_before or not crossed.any():
        delay = float("inf")  # no response to time
    else:
        delay = float(t[np.argmax(crossed)] - step_time)
    ratio = level_after / level_before if level_before != 0 else float("inf")
    return StepResponse(step_time=float(step_time), before=level_before, after=level_after,
                        input_change=float(input_change),
                        gain=(level_after - level_before) / input_change, ratio=ratio,
                        delay=delay)


def assert_step_response(time, values, *, step_time: float, before: tuple[float, float],
                         after: tuple[float, float], gain=None, ratio=None, delay=None,
                         input_change: float = 1.0, smoothing: float = 0.0,
                         crossing: float = 0.5, name: str = "signal") -> StepResponse:
    """The step response's gain, ratio and delay lie within ``(low, high)`` bounds.

    Give any of ``gain`` (signal unit per input unit), ``ratio`` (after /
    before) and ``delay`` [s] as ``(low, high)``. Returns the measurement.
    """
    __tracebackhide__ = True  # pytest shows the message, not these lines
    response = measure_step_response(time, values, step_time=step_time, before=before,
                                     after=after, input_change=input_change,
                                     smoothing=smoothing, crossing=crossing)
    failures = []
    for label, bounds, value, unit in (("gain", gain, response.gain, ""),
                                       ("ratio after/before", ratio, response.ratio, ""),
                                       ("delay", delay, response.delay, " s")):
        if bounds is None:
            continue
        low, high = bounds
        if not (low <= value <= high):
            failures.append(f"{label} {value:.4g}{unit} outside [{low:g}, {high:g}]{unit}")
    if failures:
        raise AssertionError(
            f"step response of {name!r} to the step at t = {step_time:g} s: "
            + "; ".join(failures)
            + f". Measured: level {response.before:.6g} before (mean over "
              f"[{before[0]:g}, {before[1]:g}) s), {response.after:.6g} after (mean over "
              f"[{after[0]:g}, {after[1]:g}) s), input change {input_change:g}, delay to "
              f"{crossing:.0%} of the change (smoothed over {smoothing:g} s) "
              f"{response.delay:.4g} s.")
    return response
