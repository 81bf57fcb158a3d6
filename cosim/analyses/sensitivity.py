"""Sensitivity of the MWD identification and the grindability backtracking to tracking errors.

Source: paper sections "Introduction" and "Simulator" (the simulator is used
"for understanding the sensitivity to tracking errors") and "Identification
of hardness from measurement-while-drilling" (a location error
R(-dx, dx), uniform, between where a particle really comes from and where it
is recorded to come from; the paper uses dx = 12.5 m).

A tracking error is modelled as a perturbed recorded origin,
x_n' = x_n + R(-dx, dx), for a sweep of dx and several seeds. The run
itself is not repeated: the particles' true states, the torque and the mill
signals stay those of the run, only the recorded origins change, so each
point of the sweep costs one analysis, not one simulation.

* MWD: the particle's MWD signal is the signal logged at its recorded
  origin, s_n = h(x_n')**beta_true; beta is refitted (``mwd.fit_mwd_exponent``).
* Grindability: particles are assigned to blocks by x_n' and the block
  grindability is reconciled again (``grindability.backtrack``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from cosim import batch, jsonio
from cosim.analyses import grindability, mwd
from cosim.errors import ValidationError
from cosim.numerics import power


def perturbed_origins(x: pd.Series, dx: float, rng: np.random.Generator) -> pd.Series:
    """Recorded origins x' = x + R(-dx, dx) [m] (uniform), by particle id."""
    if not (np.isfinite(dx) and dx >= 0):
        raise ValidationError("dx", "finite and >= 0 m", f"got {dx!r}")
    noise = rng.uniform(-dx, dx, len(x)) if dx > 0 else 0.0
    return pd.Series(x.to_numpy(dtype=np.float64) + noise, index=x.index)


def _check_sweep(dxs, seeds) -> tuple[np.ndarray, list[int]]:
    dxs = np.asarray(dxs, dtype=np.float64)
    if dxs.ndim != 1 or dxs.size == 0 or np.any(~np.isfinite(dxs)) or np.any(dxs < 0):
        raise ValidationError("dxs", "a non-empty list of location errors >= 0 m")
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValidationError("seeds", "at least one seed")
    return dxs, seeds


def _mwd_point(*, dx: float, seed: int, times, torque, stays, origins, beta_true: float,
               fit_scale: bool, k_cr) -> dict:
    """beta_fit for one (dx, seed) of the sweep (one task of its batch)."""
    rng = np.random.default_rng(seed)
    signals = [power(profile(perturbed_origins(x, dx, rng).to_numpy()), beta_true)
               for x, profile in origins.values()]
    index = np.concatenate([x.index.to_numpy() for x, _ in origins.values()])
    survey = pd.Series(np.concatenate(signals), index=index)
    fit = mwd.fit_mwd_exponent(times, torque, stays, survey, fit_scale=fit_scale, k_cr=k_cr)
    return {"beta_fit": fit.beta, "beta_error": abs(fit.beta - beta_true)}


def _sweep(point, common: dict, dxs, seeds, executor, label: str) -> tuple[pd.DataFrame, list]:
    """Rows (dx, seed, point's values) of the finished points, in sweep order, and
    the failed points (``cosim.batch.summary``)."""
    tasks = [batch.Task(f"dx={dx:g} m, seed {seed}", point, {"dx": float(dx)}, seed=seed)
             for dx in dxs for seed in seeds]
    own = executor is None
    executor = batch.LocalExecutor(1) if own else executor
    try:
        records = batch.run_batch(tasks, executor, common=common, label=label,
                                  progress=not own)
    finally:
        if own:
            executor.close()
    rows = [{"dx": r["inputs"]["dx"], "seed": r["seed"], **r["value"]}
            for r in records if r["status"] == "done"]
    return pd.DataFrame(rows), batch.summary(records)["failed"]


def mwd_sensitivity(times, torque, stays: pd.DataFrame, origins: dict, *, dxs, seeds,
                    beta_true: float = 0.4, fit_scale: bool = False,
                    k_cr=None, executor=None) -> pd.DataFrame:
    """beta_fit against the location error dx.

    Parameters
    ----------
    times, torque :
        Observed crusher torque [N m] at times [s].
    stays : DataFrame
        Crusher-zone residence intervals (``tracking.residence_intervals``).
    origins : dict
        ``{source: (x, profile)}``: the true origins x [m] (Series by particle
        id, the source's local mining coordinate) and the source's hardness
        profile h(x) (``cosim.blockmodel``).
    dxs, seeds :
        The sweep of location errors [m] and the seeds for each.
    beta_true : float
        Exponent of the true relation s = h**beta_true.
    fit_scale, k_cr :
        As in ``mwd.fit_mwd_exponent``.
    executor : cosim.batch.Executor or None
        Runs the points (default: one after the other in this process).

    Returns a DataFrame with ``dx``, ``seed``, ``beta_fit`` and ``beta_error``
    (``attrs["failed"]``: the points that raised, left out).
    """
    dxs, seeds = _check_sweep(dxs, seeds)
    common = {"times": times, "torque": torque, "stays": stays, "origins": origins,
              "beta_true": beta_true, "fit_scale": fit_scale, "k_cr": k_cr}
    frame, failed = _sweep(_mwd_point, common, dxs, seeds, executor, "sensitivity: MWD")
    frame.attrs["failed"] = failed
    return frame


def _final_grindability(origins: pd.Series, *, signals, feed, product, start, block_length,
                        n_blocks, block_mass, window, alpha0) -> np.ndarray:
    block_of = pd.Series(grindability.block_index(origins.to_numpy(), start, block_length,
                                                  n_blocks), index=origins.index)
    return grindability.backtrack(signals, feed, product, block_of, block_mass,
                                  window=window, alpha0=alpha0)["final"]


def _grindability_point(*, dx: float, seed: int, x: pd.Series, block_hardness, reference,
                        **backtrack) -> dict:
    """corr and rel_deviation for one (dx, seed) of the sweep (one task)."""
    g = _final_grindability(perturbed_origins(x, dx, np.random.default_rng(seed)), **backtrack)
    return {"corr": float(np.corrcoef(g, block_hardness)[0, 1]),
            "rel_deviation": float(np.sqrt(np.mean((g / reference - 1.0) ** 2)))}


def grindability_sensitivity(signals: pd.DataFrame, feed: pd.DataFrame, product: pd.DataFrame,
                             x: pd.Series, *, start: float, block_length: float,
                             n_blocks: int, block_mass, block_hardness, dxs, seeds,
                             window: float = 30.0, alpha0: float = 0.1,
                             executor=None) -> pd.DataFrame:
    """Block grindability against the location error dx.

    ``x`` holds the true origins [m] of the particles of the backtracked
    source (Series by particle id); ``block_hardness`` the true mean
    hardness of each block. Per (dx, seed): ``corr`` (Pearson correlation of
    the final block grindability with the block hardness, over all blocks:
    a blurred origin spreads a block's mass over its neighbours, so the
    weights alpha_i shrink with dx and a minimum-weight criterion would drop
    exactly the blocks the sweep is about) and ``rel_deviation`` (RMS of the
    final block grindability relative to its unperturbed value). The points
    run on ``executor`` as in ``mwd_sensitivity``.
    """
    dxs, seeds = _check_sweep(dxs, seeds)
    backtrack = {"signals": signals, "feed": feed, "product": product, "start": start,
                 "block_length": block_length, "n_blocks": n_blocks,
                 "block_mass": block_mass, "window": window, "alpha0": alpha0}
    common = {**backtrack, "x": x, "block_hardness": np.asarray(block_hardness, np.float64),
              "reference": _final_grindability(x, **backtrack)}
    frame, failed = _sweep(_grindability_point, common, dxs, seeds, executor,
                           "sensitivity: grindability")
    frame.attrs["failed"] = failed
    return frame


# ------------------------------------------------------------------ reproduce
DESCRIPTION = ("sensitivity of beta_fit and the block grindability to a location error dx "
               "in the recorded origins (sweep 0-30 m, seeds as error bars)")
FULL_DXS = (0.0, 2.5, 5.0, 7.5, 10.0, 12.5, 15.0, 20.0, 25.0, 30.0)
"""Location errors of the full sweep [m]."""
QUICK_DXS = (0.0, 12.5, 25.0)
"""Location errors of ``--quick`` [m]."""
FULL_SEEDS = (1, 2, 3, 4, 5)
QUICK_SEEDS = (1, 2, 3)


def _spread(frame: pd.DataFrame, column: str) -> dict:
    grouped = frame.groupby("dx")[column]
    return {f"{dx:g}": {"mean": float(m), "std": float(s)}
            for dx, m, s in zip(grouped.mean().index, grouped.mean(), grouped.std(ddof=0))}


def analyse(run, *, dxs, seeds, window: float = 30.0,
            executor=None) -> tuple[dict, pd.DataFrame, pd.DataFrame]:
    """Both sweeps on a ``profile_run.ProfileRun``, their points on ``executor``
    (``cosim.batch``; default: in this process); (summary, mwd sweep,
    grindability sweep)."""
    from cosim.analyses.profile_run import MWD_BETA
    from cosim.analyses.tracking import residence_intervals

    stays = residence_intervals(run.particles, "crusher_zone")
    survey = run.survey
    origins = {name: (survey.loc[survey["source"] == name, "x"], run.profiles[name])
               for name in run.profiles}
    mwd_sweep = mwd_sensitivity(run.times, run.timeseries["crusher_fmu.torque"].to_numpy(),
                                stays, origins, dxs=dxs, seeds=seeds, beta_true=MWD_BETA,
                                k_cr=mwd.run_coefficients(run.config), executor=executor)
    signals, feed, product = grindability.mill_inputs(run, window)
    _, mass, hardness = grindability.left_blocks(
        run.particles, first_cell=grindability.profile_first_cell(run))
    n_blocks = int(np.argmin(mass > 0)) if np.any(mass <= 0) else mass.size
    x = survey.loc[survey["source"] == "left", "x"]
    grind_sweep = grindability_sensitivity(
        signals, feed, product, x,
        start=grindability.profile_first_cell(run) * grindability.BLOCK_LENGTH_M,
        block_length=grindability.BLOCK_LENGTH_M,
        n_blocks=n_blocks, block_mass=mass[:n_blocks], block_hardness=hardness[:n_blocks],
        dxs=dxs, seeds=seeds, window=window, alpha0=grindability.ALPHA0, executor=executor)
    summary = {"dxs_m": [float(d) for d in dxs], "seeds": [int(s) for s in seeds],
               "beta_fit": _spread(mwd_sweep, "beta_fit"),
               "beta_error": _spread(mwd_sweep, "beta_error"),
               "corr_grindability_vs_hardness": _spread(grind_sweep, "corr"),
               "block_grindability_rel_deviation": _spread(grind_sweep, "rel_deviation"),
               "blocks": n_blocks,
               "failed_points": mwd_sweep.attrs["failed"] + grind_sweep.attrs["failed"]}
    return summary, mwd_sweep, grind_sweep


def plot(mwd_sweep: pd.DataFrame, grind_sweep: pd.DataFrame, out, run: str | None = None) -> list:
    """Error against dx with the seeds' spread as error bars; ``run`` names the runs."""
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.4))
    panels = [(mwd_sweep, "beta_error", "|beta_fit - 0.4| [-]"),
              (grind_sweep, "corr", "corr(block grindability, hardness) [-]"),
              (grind_sweep, "rel_deviation", "block grindability: RMS rel. change [-]")]
    for ax, (frame, column, label) in zip(axes, panels):
        grouped = frame.groupby("dx")[column]
        seeds = int(frame.groupby("dx").size().max())
        ax.errorbar(grouped.mean().index, grouped.mean(), yerr=grouped.std(ddof=0), fmt="o-",
                    capsize=3, label=f"mean over {seeds} seeds, bars: standard deviation")
        ax.set_xlabel("location error dx [m]")
        ax.set_ylabel(label)
    # guides to read the panels against, not pass/fail limits
    axes[0].axhline(0.01, color="gray", ls=":", lw=1, label="guide: 0.01")
    axes[1].axhline(-0.8, color="gray", ls=":", lw=1, label="guide: -0.8")
    for ax in axes:
        plotstyle.legend(ax, fontsize=7)
    plotstyle.title(fig, "Sensitivity to the location error of the tracking", run)
    fig.tight_layout()
    return [plotstyle.save(fig, Path(out) / "sensitivity.png")]


def reproduce(out_dir, *, quick: bool = False, progress: bool = True, seed: int | None = None,
              executor=None):
    """One quadratic-profile run, then both sweeps (their points on ``executor``,
    ``cosim.batch``; default: in this process); (summary, failed checks)."""
    import sys

    from cosim.analyses.profile_run import SCENARIO, output_folder, run_profile, scenario_config
    from cosim.plotstyle import run_label

    out = output_folder(out_dir)
    until = grindability.QUICK_UNTIL_S if quick else grindability.FULL_UNTIL_S
    run = run_profile(out / "run", until=until, config=scenario_config(quick=quick), seed=seed,
                      progress=progress and "sensitivity run")
    dxs, seeds = (QUICK_DXS, QUICK_SEEDS) if quick else (FULL_DXS, FULL_SEEDS)
    if progress:
        print(f"sensitivity: {len(dxs)} location errors x {len(seeds)} seeds "
              "(beta refit and block reconciliation each)", file=sys.stderr, flush=True)
    summary, mwd_sweep, grind_sweep = analyse(run, dxs=dxs, seeds=seeds, executor=executor)
    mwd_sweep.to_csv(out / "mwd_sweep.csv", index=False)
    grind_sweep.to_csv(out / "grindability_sweep.csv", index=False)
    summary.update(quick=quick, simulated_s=until, seed=run.config["simulation"]["seed"],
                   wall_s=run.run_summary["wall_s"],
                   figures=[p.name for p in plot(
                       mwd_sweep, grind_sweep, out,
                       run_label(run.config, scenario=Path(SCENARIO).stem)
                       + f", seeds {list(seeds)} of the location error")])
    failed = [f"point {p['name']} failed: {p['error']}" for p in summary["failed_points"]]
    error = mwd_sweep.groupby("dx")["beta_error"].mean()
    if not error.iloc[0] <= 0.005:
        failed.append(f"beta error without location error {error.iloc[0]:.4f} > 0.005")
    if not error.iloc[-1] > error.iloc[0]:
        failed.append("beta error does not grow with the location error")
    summary["checks_failed"] = failed
    jsonio.write(out / "summary.json", summary, indent=2, sort_keys=True)
    return summary, failed
