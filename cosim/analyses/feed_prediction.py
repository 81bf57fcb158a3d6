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

import numpy as np
import pandas as pd

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

