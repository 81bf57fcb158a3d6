"""Grindability in the mill (Bond work index) and its backtracking to ore blocks.

Source: paper section "Backtracking the grindability".

Bond ball-mill work index (Bond 1961). The specific work is measured as

    W(t) = <P_gr> / <mdot_gr-out>        [J/kg]

with <.> a trailing moving average over the window t_av [s], P_gr the mill
power [W] and mdot_gr-out the product flow [kg/s]; D80 [m] is the 80 %
passing size of the mass entering (F80) and leaving (P80) the mill in the
same window. The work index BWI [kWh/t] follows from

    W[J/kg] = 3.6 BWI (10/sqrt(P80[m]) - 10/sqrt(F80[m]))

**Erratum.** The paper prints W = (BWI/3.6) (10/sqrt(D80out) - 10/sqrt(D80in))
with D80 in metres. Bond's law is W[kWh/t] = BWI[kWh/t] (10/sqrt(P80[um]) -
10/sqrt(F80[um])); with 1 kWh/t = 3600 J/kg and sqrt(D[um]) = 1000 sqrt(D[m])
the factor is 3600/1000 = 3.6 multiplying, not dividing: the printed BWI/3.6
is a unit slip (DESIGN.md section 5a). The grindability is G = 1/BWI [t/kWh].

Block reconciliation, paper eq. (grindability_backtracking): with an a
priori estimate G_i^0 for block i and grindabilities G(t_k) observed at the
mill at times t_1..t_k,

    G_i(t_k) = (alpha_i^0 G_i^0 + sum_{k'<=k} alpha_i(t_k') G(t_k'))
               / (alpha_i^0 + sum_{k'<=k} alpha_i(t_k'))

    alpha_i(t_k) = <m_gr^i>(t_k)**2 / (m_i^0 <m_gr>(t_k))

<m_gr^i> [kg] the (moving-averaged) mass in the mill that originates from
block i, <m_gr> [kg] all mass in the mill, m_i^0 [kg] the mass of block i,
alpha_i^0 [-] the confidence in the a priori estimate (paper: 0.1; blocks of
10 m). The observation times t_k are spaced by the averaging window, so
consecutive observations do not share samples.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from cosim.analyses.tracking import F_COLUMNS, moving_average, occupancy_sum, windowed_sums
from cosim.errors import ValidationError
from cosim.sizes import d_passing

JOULES_PER_KG_PER_KWH_PER_T = 3600.0
"""1 kWh/t = 3600 J/kg."""


def bond_work_index(work, f80, p80) -> np.ndarray:
    """BWI [kWh/t] from specific work ``work`` [J/kg] and F80, P80 [m].

    BWI = W / (3.6 (10/sqrt(P80) - 10/sqrt(F80))) (see the module docstring
    for the erratum). NaN where P80 >= F80 (no size reduction to measure).
    """
    work, f80, p80 = (np.asarray(a, dtype=np.float64) for a in (work, f80, p80))
    with np.errstate(invalid="ignore", divide="ignore"):
        reduction = 10.0 / np.sqrt(p80) - 10.0 / np.sqrt(f80)
        return np.where(reduction > 0, work / (3.6 * reduction), np.nan)


def bond_signals(times, power, feed: pd.DataFrame, product: pd.DataFrame,
                 window: float = 30.0) -> pd.DataFrame:
    """Specific work, F80, P80, BWI and grindability at the mill over time.

    Parameters
    ----------
    times : array_like
        Sample times [s], ascending (e.g. the time series index).
    power : array_like
        Mill power P_gr [W] at ``times``.
    feed, product : DataFrame
        Event-store particle rows of the material entering the mill and of
        the product leaving it (``time``, ``mass``, ``f0``..``f15``).
    window : float
        Moving-average window t_av [s] (default 30 s).

    Returns a DataFrame with ``time``, ``power_w``, ``product_rate_kg_s``,
    ``work_j_kg``, ``f80_m``, ``p80_m``, ``bwi_kwh_t`` and ``grindability_t_kwh``.
    """
    if not window > 0:
        raise ValidationError("window", "> 0 s", f"got {window!r}")
    times = np.asarray(times, dtype=np.float64)
    power_avg = moving_average(power, times, window)
    out_mass = windowed_sums(product["time"], product["mass"], times, window)
    rate = out_mass / window

    def d80(rows: pd.DataFrame) -> np.ndarray:
        mf = windowed_sums(rows["time"], rows[F_COLUMNS].to_numpy() * rows["mass"].to_numpy()[:, None],
                           times, window)
        total = mf.sum(axis=1)
        out = np.full(times.size, np.nan)
        ok = total > 0
        if ok.any():
            out[ok] = d_passing(mf[ok] / total[ok, None], 0.8)
        return out

    f80, p80 = d80(feed), d80(product)
    with np.errstate(invalid="ignore", divide="ignore"):
        work = np.where(rate > 0, power_avg / rate, np.nan)
    bwi = bond_work_index(work, f80, p80)
    with np.errstate(invalid="ignore", divide="ignore"):
        grindability = np.where(bwi > 0, 1.0 / bwi, np.nan)
    return pd.DataFrame({"time": times, "power_w": power_avg, "product_rate_kg_s": rate,
                         "work_j_kg": work, "f80_m": f80, "p80_m": p80, "bwi_kwh_t": bwi,
                         "grindability_t_kwh": grindability})


def block_index(x, start: float, block_length: float = 10.0, n_blocks: int = 10) -> np.ndarray:
    """Block i = floor((x - start) / block_length) of origins ``x`` [m]; -1 outside."""
    if not block_length > 0:
        raise ValidationError("block_length", "> 0 m", f"got {block_length!r}")
    i = np.floor((np.asarray(x, dtype=np.float64) - start) / block_length).astype(np.int64)
    return np.where((i >= 0) & (i < n_blocks), i, -1)


def mill_mass_by_block(times, feed: pd.DataFrame, product: pd.DataFrame, block_of: pd.Series,
                       n_blocks: int) -> tuple[np.ndarray, np.ndarray]:
    """Mass in the mill [kg] per block of origin (T, n_blocks) and in total (T,).

    Held mass = mass that entered up to t minus mass that left as product up
    to t, per block, so it holds even when a particle leaves in parts.
    ``block_of`` maps particle id to block (-1: from no block).
    """
    def by_block(rows: pd.DataFrame, sign: float) -> tuple[np.ndarray, np.ndarray]:
        blocks = block_of.reindex(rows["particle_id"].to_numpy()).fillna(-1).to_numpy(np.int64)
        onehot = np.zeros((len(rows), n_blocks + 1))
        onehot[np.arange(len(rows)), np.where(blocks >= 0, blocks, n_blocks)] = 1.0
        t = rows["time"].to_numpy(dtype=np.float64)
        # an event at t counts from t on: a stay [t, inf)
        held = occupancy_sum(t, np.full(t.size, np.inf),
                             sign * rows["mass"].to_numpy()[:, None] * onehot, times)
        return held[:, :n_blocks], held.sum(axis=1)

    times = np.asarray(times, dtype=np.float64)
    fin, tin = by_block(feed, 1.0)
    fout, tout = by_block(product, -1.0)
    return np.clip(fin + fout, 0.0, None), np.clip(tin + tout, 0.0, None)


def reconcile(grindability, block_mass_in_mill, mill_mass, block_mass, prior,
              alpha0: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Paper eq. (grindability_backtracking) for observations k = 1..K.

    Parameters
    ----------
    grindability : (K,)
        Observed G(t_k) [t/kWh]; NaN observations are skipped.
    block_mass_in_mill : (K, B)
        <m_gr^i>(t_k) [kg].
    mill_mass : (K,)
        <m_gr>(t_k) [kg].
    block_mass : (B,)
        m_i^0 [kg], > 0.
    prior : (B,) or float
        G_i^0 [t/kWh].
    alpha0 : float
        Confidence alpha_i^0 [-] in the prior (paper: 0.1).

    Returns ``(G, alpha_sum)``: G_i(t_k) (K, B) and the cumulative
    observation weight sum_{k'<=k} alpha_i(t_k') (K, B).
    """
    g = np.asarray(grindability, dtype=np.float64)
    mi = np.asarray(block_mass_in_mill, dtype=np.float64)
    m = np.asarray(mill_mass, dtype=np.float64)
    m0 = np.asarray(block_mass, dtype=np.float64)
    if np.any(~(m0 > 0)):
        raise ValidationError("block_mass", "> 0 kg for every block")
    if not alpha0 >= 0:
        raise ValidationError("alpha0", ">= 0", f"got {alpha0!r}")
    if mi.shape != (g.size, m0.size) or m.shape != g.shape:
        raise ValidationError("block_mass_in_mill", f"shape ({g.size}, {m0.size})",
                              f"got {mi.shape} (mill_mass {m.shape})")
    prior = np.broadcast_to(np.asarray(prior, dtype=np.float64), m0.shape)
    ok = np.isfinite(g) & (m > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        alpha = np.where(ok[:, None], mi ** 2 / (m0[None, :] * m[:, None]), 0.0)
    alpha_sum = np.cumsum(alpha, axis=0)
    weighted = np.cumsum(alpha * np.where(ok, g, 0.0)[:, None], axis=0)
    return (alpha0 * prior + weighted) / (alpha0 + alpha_sum), alpha_sum


def backtrack(signals: pd.DataFrame, feed: pd.DataFrame, product: pd.DataFrame,
              block_of: pd.Series, block_mass, *, window: float = 30.0, prior=None,
              alpha0: float = 0.1) -> dict:
    """Observed grindability at the mill backtracked to blocks (paper Figs. grindability,
    block_grindability).

    ``signals`` is ``bond_signals`` output; observations are taken every
    ``window`` seconds. ``prior`` defaults to one flat value for every block,
    the median observed grindability (an uninformed a priori estimate, so
    any structure in the result comes from the mill). Returns a dict with
    ``times`` (K,), ``block_grindability`` (K, B) history, ``alpha_sum``
    (K, B), ``final`` (B,) and ``prior`` (B,).
    """
    block_mass = np.asarray(block_mass, dtype=np.float64)
    n_blocks = block_mass.size
    t_all = signals["time"].to_numpy()
    held_blocks, held_total = mill_mass_by_block(t_all, feed, product, block_of, n_blocks)
    avg_blocks = np.column_stack([moving_average(held_blocks[:, i], t_all, window)
                                  for i in range(n_blocks)])
    avg_total = moving_average(held_total, t_all, window)
    g_all = signals["grindability_t_kwh"].to_numpy()
    pick = _every(t_all, window)
    g = g_all[pick]
    if prior is None:
        finite = g[np.isfinite(g)]
        if finite.size == 0:
            raise ValidationError("signals", "some finite grindability observations",
                                  "the mill produced nothing measurable")
        prior = float(np.median(finite))
    history, alpha_sum = reconcile(g, avg_blocks[pick], avg_total[pick], block_mass, prior,
                                   alpha0)
    return {"times": t_all[pick], "block_grindability": history, "alpha_sum": alpha_sum,
            "final": history[-1], "prior": np.broadcast_to(prior, block_mass.shape).copy(),
            "observed": g}


def _every(times: np.ndarray, spacing: float) -> np.ndarray:
    """Indices of samples spaced at least ``spacing`` [s] apart, starting one window in."""
    picks, next_t = [], times[0] + spacing if times.size else 0.0
    # a plain loop over the (few thousand) samples of a time series, not over particles
    for i, t in enumerate(times):
        if t >= next_t - 1e-9:
            picks.append(i)
            next_t = t + spacing
    return np.asarray(picks, dtype=np.int64)
