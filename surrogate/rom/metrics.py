"""Accuracy metrics of a storage model against the DEM.

Source: the paper's "tracking accuracy of 10 %" (section "Integration test")
made precise as in issue 10:

- Tracking error: the outflow is cut into consecutive windows of ``window``
  seconds (default 30 s). In each window w the outflow mass per incoming
  tracking id gives a composition p_w (mass fractions). The distance of two
  runs a, b is the total-variation distance TV_w = 1/2 sum_i |p_w,i - q_w,i|
  (0 identical composition, 1 disjoint), averaged over the windows in which
  either run discharged mass (a window where only one run discharged counts
  as 1).
- Velocity-field relative error: |V_model - V_ref| / |V_ref| (Frobenius
  norms over all cells and snapshots, mass-weighted by the reference mass
  field so empty cells do not count).
- Outflow signal error: mean absolute difference of the 30 s moving averages
  of an outflow attribute (grade, hardness; mass-weighted per 1 s bin).

An outflow record is a dict of equal-length arrays ``time`` [s],
``tracking_id``, ``mass`` [kg] and attributes such as ``grade``,
``hardness``, one row per discharged particle.
"""

from __future__ import annotations

import numpy as np

WINDOW_S = 30.0
"""Default window [s] of the outflow compositions and signals (the paper's 30 s
funnel-zone horizon)."""


def window_compositions(outflow: dict, t_start: float, t_end: float, window: float = WINDOW_S):
    """Mass per (window, tracking id): ``(matrix (W, K), tracking ids (K,))``."""
    edges = np.arange(t_start, t_end + 1e-9, window)
    if edges.size < 2:
        edges = np.array([t_start, t_end])
    time = np.asarray(outflow["time"], dtype=np.float64)
    inside = (time >= edges[0]) & (time < edges[-1])
    w = np.searchsorted(edges, time[inside], side="right") - 1
    tids, k = np.unique(np.asarray(outflow["tracking_id"])[inside], return_inverse=True)
    matrix = np.zeros((edges.size - 1, tids.size))
    np.add.at(matrix, (w, k), np.asarray(outflow["mass"], dtype=np.float64)[inside])
    return matrix, tids


def window_distances(model: dict, reference: dict, t_start: float, t_end: float,
                     window: float = WINDOW_S) -> np.ndarray:
    """Total-variation distance of the two runs' outflow compositions in each
    window in which either discharged (1 where only one did)."""
    a, ids_a = window_compositions(model, t_start, t_end, window)
    b, ids_b = window_compositions(reference, t_start, t_end, window)
    ids = np.union1d(ids_a, ids_b)
    full_a = np.zeros((a.shape[0], ids.size))
    full_b = np.zeros((b.shape[0], ids.size))
    full_a[:, np.searchsorted(ids, ids_a)] = a
    full_b[:, np.searchsorted(ids, ids_b)] = b
    mass_a, mass_b = full_a.sum(axis=1), full_b.sum(axis=1)
    used = (mass_a > 0) | (mass_b > 0)
    p = full_a[used] / np.where(mass_a[used] > 0, mass_a[used], 1.0)[:, None]
    q = full_b[used] / np.where(mass_b[used] > 0, mass_b[used], 1.0)[:, None]
    tv = 0.5 * np.abs(p - q).sum(axis=1)
    tv[(mass_a[used] == 0) | (mass_b[used] == 0)] = 1.0
    return tv


def tracking_error(model: dict, reference: dict, t_start: float, t_end: float,
                   window: float = WINDOW_S) -> float:
    """Mean total-variation distance of the per-window outflow compositions
    (``window_distances``; NaN if neither run discharged)."""
    tv = window_distances(model, reference, t_start, t_end, window)
    return float(tv.mean()) if tv.size else float("nan")


def velocity_field_rel_error(predicted, reference, reference_mass) -> float:
    """Mass-weighted relative error of velocity fields ``(S, ny, nx, 2)``."""
    weight = np.sqrt(np.asarray(reference_mass, dtype=np.float64))[..., None]
    diff = np.linalg.norm(weight * (np.asarray(predicted) - np.asarray(reference)))
    norm = np.linalg.norm(weight * np.asarray(reference))
    return float(diff / norm) if norm > 0 else float("nan")


def moving_average_signal(outflow: dict, attribute: str, t_start: float, t_end: float,
                          window: float = WINDOW_S, bin_s: float = 1.0) -> np.ndarray:
    """Moving average (``window`` s) of the outflow's mass-weighted ``attribute``
    per ``bin_s`` bin; NaN where no mass left within the window."""
    edges = np.arange(t_start, t_end + 1e-9, bin_s)
    time = np.asarray(outflow["time"], dtype=np.float64)
    inside = (time >= edges[0]) & (time < edges[-1])
    b = np.searchsorted(edges, time[inside], side="right") - 1
    mass = np.asarray(outflow["mass"], dtype=np.float64)[inside]
    values = np.asarray(outflow[attribute], dtype=np.float64)[inside]
    m = np.bincount(b, weights=mass, minlength=edges.size - 1)
    mv = np.bincount(b, weights=mass * values, minlength=edges.size - 1)
    kernel = np.ones(max(int(round(window / bin_s)), 1))
    m_avg = np.convolve(m, kernel)[: m.size]
    mv_avg = np.convolve(mv, kernel)[: m.size]
    return np.where(m_avg > 0, mv_avg / np.where(m_avg > 0, m_avg, 1.0), np.nan)


def outflow_signal_error(model: dict, reference: dict, attribute: str, t_start: float,
                         t_end: float, window: float = WINDOW_S) -> float:
    """Mean absolute difference of the two runs' moving-average outflow ``attribute``."""
    a = moving_average_signal(model, attribute, t_start, t_end, window)
    b = moving_average_signal(reference, attribute, t_start, t_end, window)
    both = np.isfinite(a) & np.isfinite(b)
    return float(np.abs(a[both] - b[both]).mean()) if both.any() else float("nan")
