"""Who was where, when: residence intervals and occupancy from macro-tracking events.

Source: paper section "Digital twin as a distributed particle simulation":
macro-tracking events mark a particle entering and leaving an asset, so the
set N_V(t) of particles in an asset volume at time t is known from the event
store alone. Every analysis in this package sums particle quantities over
such sets, e.g. the crusher torque (paper eq. crusher_torque) or the ore mass
in the mill per block of origin (paper eq. grindability_backtracking).

Input is the particle table of an ``EventStore`` (``EventStore.particles()``:
one row per event and particle with ``type``, ``asset``, ``time`` [s],
``particle_id``, ``mass`` [kg], ``grade``, ``hardness``, ``origin_block``,
``x``, ``y``, ``z`` [m] and ``f0``..``f15``), so the functions work on any
run's store, not only the simulator's.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from cosim.errors import ValidationError
from cosim.sizes import N_CLASSES

F_COLUMNS = [f"f{k}" for k in range(N_CLASSES)]
"""Size-fraction columns of an event-store particle table."""

_REQUIRED = ("type", "asset", "time", "particle_id", "mass")


def _check_table(table: pd.DataFrame, name: str = "particles") -> None:
    missing = [c for c in _REQUIRED if c not in table.columns]
    if missing:
        raise ValidationError(name, f"an event-store particle table with columns {list(_REQUIRED)}",
                              f"missing {missing}")


def residence_intervals(particles: pd.DataFrame, asset: str, *,
                        enter_types=("enter",), leave_types=("exit", "pass", "product"),
                        leave_asset: str | None = None) -> pd.DataFrame:
    """One row per stay of a particle in ``asset``: its state on entry, ``t_in`` and ``t_out``.

    Parameters
    ----------
    particles : DataFrame
        ``EventStore.particles()`` (or a filtered part of it).
    asset : str
        Asset whose ``enter_types`` events open a stay.
    enter_types, leave_types : tuple of str
        Event types that open and close a stay.
    leave_asset : str, optional
        Asset whose ``leave_types`` events close the stay (default ``asset``).

    Each stay is closed by the first leaving event of the same particle at
    or after its entry; a particle still inside has ``t_out = inf``. The
    columns are the entering event's (mass, grade, hardness, f0..f15, ...)
    plus ``t_in`` and ``t_out`` [s].
    """
    _check_table(particles)
    leave_asset = asset if leave_asset is None else leave_asset
    enter = particles[(particles["asset"] == asset) & particles["type"].isin(enter_types)]
    leave = particles[(particles["asset"] == leave_asset) & particles["type"].isin(leave_types)]
    if enter.empty:
        raise ValidationError("asset", "an asset with events of types " + str(list(enter_types)),
                              f"no such events for {asset!r}; assets: "
                              f"{sorted(particles['asset'].unique())}")
    enter = enter.rename(columns={"time": "t_in"}).sort_values("t_in", kind="stable")
    leave = (leave[["particle_id", "time"]].rename(columns={"time": "t_out"})
             .sort_values("t_out", kind="stable"))
    stays = pd.merge_asof(enter, leave, left_on="t_in", right_on="t_out", by="particle_id",
                          direction="forward", allow_exact_matches=True)
    stays["t_out"] = stays["t_out"].fillna(np.inf)
    return stays.drop(columns=["type", "event_id"], errors="ignore").reset_index(drop=True)


def occupancy_sum(t_in, t_out, weights, times) -> np.ndarray:
    """Sum of ``weights`` over the stays that hold at each of ``times``.

    A stay [t_in, t_out) counts at time t if t_in <= t < t_out. ``weights``
    is (N,) or (N, K); the result is (T,) or (T, K). O(N + T) per call: each
    stay adds its weight where it starts and removes it where it ends, and a
    cumulative sum over the sorted times does the rest (no loop over
    particles).
    """
    times = np.asarray(times, dtype=np.float64)
    if times.ndim != 1 or (times.size > 1 and np.any(np.diff(times) < 0)):
        raise ValidationError("times", "a 1-D array sorted ascending")
    w = np.asarray(weights, dtype=np.float64)
    single = w.ndim == 1
    w2 = w[:, None] if single else w
    start = np.searchsorted(times, np.asarray(t_in, dtype=np.float64), side="left")
    stop = np.searchsorted(times, np.asarray(t_out, dtype=np.float64), side="left")
    delta = np.zeros((times.size + 1, w2.shape[1]))
    np.add.at(delta, start, w2)
    np.add.at(delta, stop, -w2)
    out = np.cumsum(delta[:-1], axis=0)
    # where no stay holds, the running sum is zero up to round-off: make it exact
    held = np.cumsum(np.bincount(start, minlength=times.size + 1)
                     - np.bincount(stop, minlength=times.size + 1))[:-1]
    out[held == 0] = 0.0
    return out[:, 0] if single else out


def moving_average(values, times, window: float) -> np.ndarray:
    """Trailing moving average over ``window`` [s] of a sampled signal (paper eq. observation).

    The average at t is over the samples in (t - window, t]; NaN samples are
    left out.
    """
    v = np.asarray(values, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    ok = np.isfinite(v)
    csum = np.concatenate(([0.0], np.cumsum(np.where(ok, v, 0.0))))
    ccount = np.concatenate(([0], np.cumsum(ok)))
    lo = np.searchsorted(t, t - window, side="right")
    hi = np.arange(1, t.size + 1)
    count = ccount[hi] - ccount[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, (csum[hi] - csum[lo]) / np.maximum(count, 1), np.nan)


def windowed_sums(event_times, weights, times, window: float) -> np.ndarray:
    """Sum of ``weights`` of the events in the trailing window (t - window, t] at each time.

    ``weights`` (N,) or (N, K); events need not be sorted.
    """
    order = np.argsort(np.asarray(event_times, dtype=np.float64), kind="stable")
    et = np.asarray(event_times, dtype=np.float64)[order]
    w = np.asarray(weights, dtype=np.float64)[order]
    single = w.ndim == 1
    w2 = w[:, None] if single else w
    csum = np.vstack((np.zeros((1, w2.shape[1])), np.cumsum(w2, axis=0)))
    times = np.asarray(times, dtype=np.float64)
    hi = np.searchsorted(et, times, side="right")
    lo = np.searchsorted(et, times - window, side="right")
    out = csum[hi] - csum[lo]
    return out[:, 0] if single else out
