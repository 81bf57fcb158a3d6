"""Hardness from measurement-while-drilling (MWD), identified from the crusher torque.

Source: paper section "Identification of hardness from measurement-while-
drilling" with the crusher torque model of section "Simulator",
eq. (crusher_torque):

    tau_cr(t) = sum_{n in N_Vcr(t)} m_n h_n k_cr . f_n

m_n [kg] particle mass, h_n [-] hardness, f_n its 16 size fractions and
k_cr the crushing coefficients: 1.0 for the oversize classes
(d_k >= d_cr = 0.25 m) and 0.1 for the undersize. The MWD signal recorded at
the source follows s = h**beta (the paper's ground truth beta = 0.4, with a
uniform location error of 12.5 m: s_n = h(x_n + R(-dx, dx))**0.4). With the
ansatz s = h**beta the hardness of a tracked particle is h_n = s_n**(1/beta),
so the expected torque given beta is

    tau(t; beta) = c sum_{n in N_Vcr(t)} m_n s_n**(1/beta) k_cr . f_n

and beta (and optionally the scale c [N m per kg], default 1) is chosen to
minimise the squared difference to the observed torque (scipy.optimize).
Once beta is known, the hardness of material about to enter the crusher is
predicted from its MWD signal alone: h = s**(1/beta).

The set N_Vcr(t) is taken from the macro-tracking events (``enter`` and
``pass``/``exit`` of the crusher zone), the MWD signal is a per-particle
value keyed by particle id, so the fit runs on any run's time series and
event store.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import optimize

from cosim.analyses.tracking import F_COLUMNS, occupancy_sum
from cosim.errors import ValidationError
from cosim.sizes import DIAMETERS

CRUSHER_GAP = 0.25
"""Crusher gap width d_cr [m] (paper section "Simulator")."""


def crushing_coefficients(gap: float = CRUSHER_GAP, oversize: float = 1.0,
                          undersize: float = 0.1) -> np.ndarray:
    """k_cr per size class: ``oversize`` (1.0) for d_k >= gap [m], else ``undersize`` (0.1)."""
    return np.where(DIAMETERS >= gap * (1 - 1e-12), oversize, undersize)


def mwd_of(stays: pd.DataFrame, mwd: pd.Series) -> np.ndarray:
    """The MWD signal of every stay's particle; every particle must have one."""
    values = mwd.reindex(stays["particle_id"].to_numpy()).to_numpy(dtype=np.float64)
    if not np.all(np.isfinite(values) & (values > 0)):
        bad = stays["particle_id"].to_numpy()[~(np.isfinite(values) & (values > 0))]
        raise ValidationError("mwd", "a finite signal > 0 for every particle in the crusher zone",
                              f"{bad.size} particle(s) without one, e.g. id {int(bad[0])}")
    return values


def expected_torque(stays: pd.DataFrame, signal: np.ndarray, beta: float, times,
                    k_cr: np.ndarray | None = None, scale: float = 1.0) -> np.ndarray:
    """tau(t; beta) = scale * sum_{n in zone at t} m_n s_n**(1/beta) k_cr.f_n [N m]."""
    k_cr = crushing_coefficients() if k_cr is None else k_cr
    kf = stays[F_COLUMNS].to_numpy() @ k_cr
    weights = stays["mass"].to_numpy() * kf * signal ** (1.0 / beta)
    return scale * occupancy_sum(stays["t_in"].to_numpy(), stays["t_out"].to_numpy(),
                                 weights, times)


@dataclass
class MwdFit:
    """Result of ``fit_mwd_exponent``.

    beta [-]: fitted exponent of s = h**beta; scale [-]: torque scale c;
    rmse [N m]: root-mean-square torque residual; samples: time samples used.
    """

    beta: float
    scale: float
    rmse: float
    samples: int


def fit_mwd_exponent(times, torque, stays: pd.DataFrame, mwd: pd.Series, *,
                     k_cr: np.ndarray | None = None, bounds=(0.05, 2.0),
                     fit_scale: bool = False) -> MwdFit:
    """Fit beta of the ansatz s = h**beta to an observed crusher torque.

    Parameters
    ----------
    times, torque : array_like
        Sample times [s] (ascending) and observed crusher torque [N m].
    stays : DataFrame
        ``tracking.residence_intervals`` of the crusher zone.
    mwd : Series
        MWD signal [-] by particle id (the extrinsic attribute ``mwd``).
    k_cr : array (16,), optional
        Crushing coefficients (default: ``crushing_coefficients()``).
    bounds : (float, float)
        Search interval for beta (default 0.05 .. 2).
    fit_scale : bool
        Also fit the torque scale c in closed form (linear least squares for
        each beta) when the torque is known only up to a constant.

    Samples where the zone is empty and the observed torque is zero carry no
    information about beta and are dropped.
    """
    times = np.asarray(times, dtype=np.float64)
    torque = np.asarray(torque, dtype=np.float64)
    if times.shape != torque.shape or times.ndim != 1:
        raise ValidationError("torque", "a 1-D array of the same length as times",
                              f"got {torque.shape} and {times.shape}")
    finite = np.isfinite(torque)
    times, torque = times[finite], torque[finite]
    signal = mwd_of(stays, mwd)
    occupied = occupancy_sum(stays["t_in"].to_numpy(), stays["t_out"].to_numpy(),
                             np.ones(len(stays)), times) > 0
    keep = occupied | (torque != 0)
    times, torque = times[keep], torque[keep]
    if times.size < 3:
        raise ValidationError("torque", "at least 3 samples while the crusher zone holds ore",
                              f"got {times.size}")

    def residual(beta: float) -> tuple[np.ndarray, float]:
        model = expected_torque(stays, signal, beta, times, k_cr)
        scale = float(model @ torque / (model @ model)) if fit_scale else 1.0
        return scale * model - torque, scale

    result = optimize.minimize_scalar(lambda b: float(np.sum(residual(b)[0] ** 2)),
                                      bounds=bounds, method="bounded",
                                      options={"xatol": 1e-6})
    res, scale = residual(float(result.x))
    return MwdFit(beta=float(result.x), scale=scale, rmse=float(np.sqrt(np.mean(res ** 2))),
                  samples=int(times.size))


def predicted_hardness(signal, beta: float) -> np.ndarray:
    """Hardness from the MWD signal: h = s**(1/beta) [-]."""
    if not (np.isfinite(beta) and beta > 0):
        raise ValidationError("beta", "finite and > 0", f"got {beta!r}")
    return np.asarray(signal, dtype=np.float64) ** (1.0 / beta)


def zone_hardness(stays: pd.DataFrame, mwd: pd.Series, times, betas) -> pd.DataFrame:
    """Mass-weighted hardness in the zone over time: true, and predicted from MWD per beta.

    The prediction for a particle exists as soon as it is dumped at the
    hopper, before it enters the crusher zone (its MWD signal travels with
    it). Columns: ``time``, ``hardness_true``, ``hardness_beta_<beta>``.
    NaN where the zone holds nothing.
    """
    signal = mwd_of(stays, mwd)
    mass = stays["mass"].to_numpy()
    t_in, t_out = stays["t_in"].to_numpy(), stays["t_out"].to_numpy()
    columns = [stays["hardness"].to_numpy()] + [predicted_hardness(signal, b) for b in betas]
    sums = occupancy_sum(t_in, t_out, mass[:, None] * np.column_stack(columns), times)
    total = occupancy_sum(t_in, t_out, mass, times)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(total[:, None] > 0, sums / total[:, None], np.nan)
    frame = pd.DataFrame({"time": np.asarray(times, dtype=np.float64),
                          "hardness_true": means[:, 0]})
    for j, b in enumerate(betas):
        frame[f"hardness_beta_{b:g}"] = means[:, j + 1]
    return frame


def hardness_prediction_rmse(stays: pd.DataFrame, mwd: pd.Series, beta: float) -> float:
    """Mass-weighted RMS error [-] of the per-particle hardness predicted from MWD."""
    predicted = predicted_hardness(mwd_of(stays, mwd), beta)
    mass = stays["mass"].to_numpy()
    err = predicted - stays["hardness"].to_numpy()
    return float(np.sqrt(np.sum(mass * err ** 2) / np.sum(mass)))
