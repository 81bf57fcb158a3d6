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
is a unit slip (docs/architecture.md, errata). The grindability is G = 1/BWI [t/kWh].

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

from pathlib import Path

import numpy as np
import pandas as pd

from cosim import jsonio
from cosim.analyses.tracking import F_COLUMNS, moving_average, occupancy_sum, windowed_sums
from cosim.errors import ValidationError
from cosim.sizes import d_passing


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
                 window: float = 30.0, product_flow_by_class=None,
                 product_rate=None) -> pd.DataFrame:
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
    product_flow_by_class : array (T, 16), optional
        Product mass flow per size class [kg/s] at ``times`` (e.g. the mill
        FMU's escape rate times the charge mass per class). When given, P80
        is taken from it, for event stores whose product events carry the
        leaving particle's remaining size distribution rather than that of
        the escaped mass.
    product_rate : array (T,), optional
        Product flow [kg/s] at ``times`` (e.g. the mill's recorded output);
        by default the product events' masses per window.

    Returns a DataFrame with ``time``, ``power_w``, ``product_rate_kg_s``,
    ``work_j_kg``, ``f80_m``, ``p80_m``, ``bwi_kwh_t`` and ``grindability_t_kwh``.
    """
    if not window > 0:
        raise ValidationError("window", "> 0 s", f"got {window!r}")
    times = np.asarray(times, dtype=np.float64)
    power_avg = moving_average(power, times, window)
    if product_rate is None:
        rate = windowed_sums(product["time"], product["mass"], times, window) / window
    else:
        rate = moving_average(product_rate, times, window)

    def d80(rows: pd.DataFrame) -> np.ndarray:
        mf = windowed_sums(rows["time"], rows[F_COLUMNS].to_numpy() * rows["mass"].to_numpy()[:, None],
                           times, window)
        total = mf.sum(axis=1)
        out = np.full(times.size, np.nan)
        ok = total > 0
        if ok.any():
            out[ok] = d_passing(mf[ok] / total[ok, None], 0.8)
        return out

    f80 = d80(feed)
    if product_flow_by_class is None:
        p80 = d80(product)
    else:
        flow = np.asarray(product_flow_by_class, dtype=np.float64)
        if flow.shape != (times.size, len(F_COLUMNS)):
            raise ValidationError("product_flow_by_class", f"an array of shape ({times.size}, 16)",
                                  f"got {flow.shape}")
        avg = np.column_stack([moving_average(flow[:, k], times, window)
                               for k in range(flow.shape[1])])
        total = avg.sum(axis=1)
        p80 = np.full(times.size, np.nan)
        ok = total > 0
        if ok.any():
            p80[ok] = d_passing(avg[ok] / total[ok, None], 0.8)
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
              alpha0: float = 0.1, start: float | None = None) -> dict:
    """Observed grindability at the mill backtracked to blocks (paper Figs. grindability,
    block_grindability).

    ``signals`` is ``bond_signals`` output; observations are taken every
    ``window`` seconds from ``start`` [s] on (default: two windows after the
    first feed, so the mill's start-up, when it fills and the product flow
    lags the feed, is not read as grindability). ``prior`` defaults to one flat value for every block,
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
    if start is None:
        start = float(feed["time"].min()) + 2.0 * window if len(feed) else float(t_all[0])
    later = np.flatnonzero(t_all >= start)
    pick = later[_every(t_all[later], window)] if later.size else later
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
    """Indices of samples spaced at least ``spacing`` [s] apart, the first one included."""
    picks, next_t = [], times[0] if times.size else 0.0
    # a plain loop over the (few thousand) samples of a time series, not over particles
    for i, t in enumerate(times):
        if t >= next_t - 1e-9:
            picks.append(i)
            next_t = t + spacing
    return np.asarray(picks, dtype=np.int64)


# ------------------------------------------------------------------ reproduce
DESCRIPTION = ("Bond work index in the mill and the grindability backtracked to the 10 m "
               "blocks of the left source's quadratic hardness profile")
QUICK_UNTIL_S = 1250.0
"""Simulated time of ``--quick`` [s]: the narrow-face quick run mines the lead-in and the
100 m profile in about 850 s; the last blocks reach the mill through the stockpile by
about 1,150 s."""
FULL_UNTIL_S = 3300.0
"""Simulated time of the full run [s]: the profile is mined by about 2,800 s."""
BLOCK_LENGTH_M = 10.0
"""Block size [m] (paper: 10 m)."""
N_BLOCKS = 10
"""Blocks over the 100 m profile."""
ALPHA0 = 0.1
"""Confidence in the a priori grindability (paper: alpha^0 = 0.1)."""
CORR_LIMIT = -0.8
"""Largest accepted correlation of block grindability with block hardness."""


def left_blocks(particles: pd.DataFrame, source: str = "left", n_blocks: int = N_BLOCKS,
                first_cell: int = 0):
    """Block of origin by particle id (-1 outside the ``n_blocks`` blocks from block-model
    cell ``first_cell`` on), the mined mass m_i^0 [kg] and the mass-weighted true hardness
    of each block, from the appear events.

    The scenario's block model has 10 m cells, so ``origin_block`` is the block index.
    """
    appear = particles[(particles["type"] == "appear") & (particles["asset"] == source)]
    blocks = appear["origin_block"].to_numpy(np.int64) - int(first_cell)
    blocks = np.where((blocks >= 0) & (blocks < n_blocks), blocks, -1)
    block_of = pd.Series(blocks, index=appear["particle_id"].to_numpy())
    inside = blocks >= 0
    mass = np.bincount(blocks[inside], appear["mass"].to_numpy()[inside], minlength=n_blocks)
    weighted = np.bincount(blocks[inside], (appear["mass"] * appear["hardness"]).to_numpy()[inside],
                           minlength=n_blocks)
    with np.errstate(invalid="ignore", divide="ignore"):
        hardness = np.where(mass > 0, weighted / mass, np.nan)
    return block_of, mass, hardness


def profile_first_cell(run) -> int:
    """Block-model cell where the run's hardness profile starts (10 m cells)."""
    return int(round(run.profile_start / BLOCK_LENGTH_M))


def mill_inputs(run, window: float = 30.0):
    """Bond signals, feed and product rows of the mill in a ``profile_run.ProfileRun``."""
    table = run.particles
    feed = table[(table["asset"] == "mill") & (table["type"] == "enter")]
    product = table[(table["asset"] == "mill") & (table["type"] == "product")]
    ts = run.timeseries
    flow = (ts[[f"mill_fmu.escape_rate[{k}]" for k in range(16)]].to_numpy()
            * ts[[f"mill.charge_mass[{k}]" for k in range(16)]].to_numpy())
    signals = bond_signals(run.times, ts["mill_fmu.power"].to_numpy(), feed, product,
                           window=window, product_flow_by_class=flow,
                           product_rate=ts["mill.product_rate_kg_s"].to_numpy())
    return signals, feed, product


def analyse(run, window: float = 30.0) -> tuple[dict, dict]:
    """Bond signals and block reconciliation on a run; (summary, plot data)."""
    signals, feed, product = mill_inputs(run, window)
    block_of, mass, hardness = left_blocks(run.particles,
                                           first_cell=profile_first_cell(run))
    mined = mass > 0
    index = np.flatnonzero(mined)
    # only mined blocks take part (m_i^0 > 0); keep their original numbers
    renumber = np.full(N_BLOCKS, -1)
    renumber[index] = np.arange(index.size)
    local = pd.Series(np.where(block_of.to_numpy() >= 0,
                               renumber[np.clip(block_of.to_numpy(), 0, None)], -1),
                      index=block_of.index)
    result = backtrack(signals, feed, product, local, mass[mined], window=window, alpha0=ALPHA0)
    enough = result["alpha_sum"][-1] >= ALPHA0
    final = result["final"]
    corr = (float(np.corrcoef(final[enough], hardness[mined][enough])[0, 1])
            if enough.sum() >= 3 else float("nan"))
    bwi = signals["bwi_kwh_t"].to_numpy()
    summary = {
        "block_grindability": {int(i): float(g) for i, g in zip(index, final)},
        "block_hardness": {int(i): float(h) for i, h in zip(index, hardness[mined])},
        "block_alpha_sum": {int(i): float(a) for i, a in zip(index, result["alpha_sum"][-1])},
        "blocks_with_enough_mass": [int(i) for i in index[enough]],
        "corr_grindability_vs_hardness": corr,
        "prior_grindability_t_kwh": float(result["prior"][0]),
        "bwi_mean_kwh_t": float(np.nanmean(bwi)),
        "bwi_min_kwh_t": float(np.nanmin(bwi)), "bwi_max_kwh_t": float(np.nanmax(bwi)),
        "f80_mean_m": float(np.nanmean(signals["f80_m"])),
        "p80_mean_m": float(np.nanmean(signals["p80_m"])),
        "specific_work_mean_j_kg": float(np.nanmean(signals["work_j_kg"])),
        "window_s": window, "alpha0": ALPHA0, "block_length_m": BLOCK_LENGTH_M,
    }
    return summary, {"signals": signals, "result": result, "index": index,
                     "hardness": hardness[mined], "enough": enough}


BWI_NOTE = ("BWI of the idealised mill FMU: its specific-energy scale is not calibrated "
            "(real ore: about 10-20 kWh/t);\nread the changes between blocks, not the level")
"""What the figures say about the absolute BWI level."""


def plot(data: dict, out, run: str | None = None) -> list:
    """Figures in the spirit of the paper's "grindability" and "block_grindability";
    ``run`` names the run in the titles (``cosim.plotstyle.run_label``)."""
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    out = Path(out)
    signals, result = data["signals"], data["result"]
    fig, (ax, bx) = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    ax.plot(signals["time"], signals["bwi_kwh_t"], lw=0.8, color="k",
            label="BWI measured in the mill (30 s averages)")
    first = result["times"][0] if len(result["times"]) else signals["time"].iloc[0]
    ax.axvspan(signals["time"].iloc[0], first, color="0.92", label="mill start-up (not used)")
    steady = signals.loc[signals["time"] >= first, "bwi_kwh_t"].dropna()
    if len(steady):
        lo, hi = np.percentile(steady, [0.5, 99.5])
        ax.set_ylim(lo - 0.2 * (hi - lo + 1e-12), hi + 0.2 * (hi - lo + 1e-12))
    ax.set_ylabel("BWI [kWh/t]")
    ax.text(0.01, 0.02, BWI_NOTE, transform=ax.transAxes, fontsize=7, va="bottom",
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "0.8"})
    plotstyle.legend(ax, loc="upper right")
    for j, i in enumerate(data["index"]):
        bx.plot(result["times"], 1.0 / result["block_grindability"][:, j], lw=1.0,
                label=f"block {i}")
    bx.set_ylabel("backtracked 1/G_i [kWh/t]")
    bx.set_xlabel("time [s]")
    bx.legend(fontsize=7, ncol=5)
    plotstyle.title(fig, "Grindability from the mill's energy: measured BWI and the "
                    "backtracked block values", run)
    fig.tight_layout()
    paths = [plotstyle.save(fig, out / "grindability.png")]

    centres = (data["index"] + 0.5) * BLOCK_LENGTH_M     # from the profile's start
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.bar(centres, result["final"], width=0.8 * BLOCK_LENGTH_M, color=np.where(
        data["enough"], "tab:orange", "lightgray"), label="backtracked grindability G_i")
    ax.axhline(result["prior"][0], color="gray", ls=":", lw=1, label="a priori G_i^0 (flat)")
    ax.set_xlabel("block centre along the left ore body [m]")
    ax.set_ylabel("grindability G = 1/BWI [t/kWh]")
    lo = np.nanmin(result["final"])
    ax.set_ylim(lo - 0.2 * (np.nanmax(result["final"]) - lo + 1e-12), None)
    twin = ax.twinx()
    twin.grid(False)
    twin.plot(centres, data["hardness"], "o-", color="tab:blue",
              label="block hardness (right axis)")
    twin.set_ylabel("hardness [-]", color="tab:blue")
    plotstyle.legend(ax, twin, loc="lower center")
    plotstyle.title(fig, "Backtracked grindability per block\n(idealised mill: energy scale "
                    "not calibrated)", run)
    fig.tight_layout()
    paths.append(plotstyle.save(fig, out / "block_grindability.png"))
    return paths


def _run_label(run) -> str:
    from cosim.analyses.profile_run import SCENARIO
    from cosim.plotstyle import run_label

    return run_label(run.config, scenario=Path(SCENARIO).stem)


def reproduce(out_dir, *, quick: bool = False, progress: bool = True, seed: int | None = None):
    """Run the quadratic-profile scenario and backtrack the grindability; (summary, failed)."""

    from cosim.analyses.profile_run import output_folder, run_profile, scenario_config

    out = output_folder(out_dir)
    until = QUICK_UNTIL_S if quick else FULL_UNTIL_S
    run = run_profile(out / "run", until=until, config=scenario_config(quick=quick), seed=seed,
                      progress=progress and "grindability run")
    summary, data = analyse(run)
    summary.update(quick=quick, simulated_s=until, seed=run.config["simulation"]["seed"],
                   wall_s=run.run_summary["wall_s"],
                   figures=[p.name for p in plot(data, out, _run_label(run))])
    failed = []
    if len(summary["blocks_with_enough_mass"]) < N_BLOCKS:
        failed.append(f"only {len(summary['blocks_with_enough_mass'])} of {N_BLOCKS} blocks "
                      "reached the mill with enough mass")
    if not summary["corr_grindability_vs_hardness"] <= CORR_LIMIT:
        failed.append(f"corr_grindability_vs_hardness = "
                      f"{summary['corr_grindability_vs_hardness']:.3f} > {CORR_LIMIT}")
    summary["checks_failed"] = failed
    jsonio.write(out / "summary.json", summary, indent=2, sort_keys=True)
    return summary, failed
