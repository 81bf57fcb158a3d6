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

import numpy as np
import pandas as pd

from cosim.analyses import grindability, mwd
from cosim.errors import ValidationError


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


def mwd_sensitivity(times, torque, stays: pd.DataFrame, origins: dict, *, dxs, seeds,
                    beta_true: float = 0.4, fit_scale: bool = False) -> pd.DataFrame:
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

    Returns a DataFrame with ``dx``, ``seed``, ``beta_fit`` and ``beta_error``.
    """
    dxs, seeds = _check_sweep(dxs, seeds)
    rows = []
    for dx in dxs:
        for seed in seeds:
            rng = np.random.default_rng(seed)
            signals = [profile(perturbed_origins(x, dx, rng).to_numpy()) ** beta_true
                       for x, profile in origins.values()]
            index = np.concatenate([x.index.to_numpy() for x, _ in origins.values()])
            survey = pd.Series(np.concatenate(signals), index=index)
            fit = mwd.fit_mwd_exponent(times, torque, stays, survey, fit_scale=fit_scale)
            rows.append({"dx": float(dx), "seed": seed, "beta_fit": fit.beta,
                         "beta_error": abs(fit.beta - beta_true)})
    return pd.DataFrame(rows)


def grindability_sensitivity(signals: pd.DataFrame, feed: pd.DataFrame, product: pd.DataFrame,
                             x: pd.Series, *, start: float, block_length: float,
                             n_blocks: int, block_mass, block_hardness, dxs, seeds,
                             window: float = 30.0, alpha0: float = 0.1) -> pd.DataFrame:
    """Block grindability against the location error dx.

    ``x`` holds the true origins [m] of the particles of the backtracked
    source (Series by particle id); ``block_hardness`` the true mean
    hardness of each block. Per (dx, seed): ``corr`` (Pearson correlation of
    the final block grindability with the block hardness, over the blocks
    whose observation weight reached alpha0) and ``rel_deviation`` (RMS of
    the final block grindability relative to its unperturbed value).
    """
    dxs, seeds = _check_sweep(dxs, seeds)
    block_hardness = np.asarray(block_hardness, dtype=np.float64)

    def final(origins: pd.Series) -> tuple[np.ndarray, np.ndarray]:
        block_of = pd.Series(grindability.block_index(origins.to_numpy(), start, block_length,
                                                      n_blocks), index=origins.index)
        result = grindability.backtrack(signals, feed, product, block_of, block_mass,
                                        window=window, alpha0=alpha0)
        return result["final"], result["alpha_sum"][-1] >= alpha0

    reference, _ = final(x)
    rows = []
    for dx in dxs:
        for seed in seeds:
            g, enough = final(perturbed_origins(x, dx, np.random.default_rng(seed)))
            corr = (float(np.corrcoef(g[enough], block_hardness[enough])[0, 1])
                    if enough.sum() >= 3 else float("nan"))
            rows.append({"dx": float(dx), "seed": seed, "corr": corr,
                         "rel_deviation": float(np.sqrt(np.mean((g / reference - 1.0) ** 2)))})
    return pd.DataFrame(rows)
