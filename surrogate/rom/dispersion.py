"""Dispersion of the bulk about the mean flow, measured on DEM and applied in the ROM.

Source: the ROM of the paper (sections "Digital twin as a distributed
particle simulation" and "Integration test"; Wallin and Servin 2021)
advects bulk particles with the predicted *mean* velocity field. In the DEM
the particles also wander about that mean (contacts rearrange, shear zones
mix), which spreads each lot's residence time; advection alone leaves the
ROM's outflow too close to plug flow. We add the classic closure of
hydrodynamic dispersion, a random walk whose diffusivity scales with the
local flow speed:

    D(x) = alpha |v(x)|   [m^2/s],

with alpha the dispersivity [m]. Each advection step of h seconds moves
every bulk particle by sqrt(2 D h) N(0, 1) in x and in y.

Measurement (``dispersion_fit``): over the same window tau as the velocity
samples (``doe.VELOCITY_WINDOW``), a particle's residual r is its
displacement minus the mass-weighted linear fit of displacement on position
within its cell (the mean flow and its gradient across the cell, which the
ROM's interpolated field carries, are not dispersion); per cell with at
least ``MIN_PARTICLES`` particles, D_c = <|r|^2> n / (n - 3) / (4 tau)
(2-D random walk; three fitted coefficients per axis) and
U_c = |mean displacement| / tau.
alpha is the mass-weighted least-squares slope of D_c on U_c over all
training samples: alpha = sum(w D U) / sum(w U^2), each sample contributing
its two sums (``dispersion_fit`` returns them, ``dispersivity`` adds them).
``minetwin rom train`` prints the value it measured (about 0.01 m, a
fortieth of a particle diameter per metre travelled, on the quick design).
"""

from __future__ import annotations

import numba
import numpy as np

from surrogate.rom.advect import sample
from surrogate.rom.grid import Grid

MIN_PARTICLES = 6
"""Cells with fewer particles in a sample do not enter the fit."""


def dispersion_fit(grid: Grid, before: dict, after: dict) -> np.ndarray:
    """The two least-squares sums ``[sum(w D U), sum(w U^2)]`` of one pair of
    bulk snapshots (dicts with ``time``, ``id``, ``position``, ``mass``)."""
    tau = float(after["time"]) - float(before["time"])
    _, ia, ib = np.intersect1d(before["id"], after["id"], assume_unique=True,
                               return_indices=True)
    start = np.asarray(before["position"])[ia]
    shift = np.asarray(after["position"])[ib] - start
    mass = np.asarray(before["mass"])[ia]
    # binned where they start: binning by the mid-point would select, within a
    # cell, the particles whose random step fits their start offset
    cells = grid.cell_index(start)
    inside = cells >= 0
    cells, shift, mass = cells[inside], shift[inside], mass[inside]
    start = start[inside]
    total = np.bincount(cells, weights=mass, minlength=grid.n_cells)
    count = np.bincount(cells, minlength=grid.n_cells)
    safe = np.where(total > 0, total, 1.0)

    def cell_mean(values):
        return np.stack([np.bincount(cells, weights=mass * values[:, k], minlength=grid.n_cells)
                         for k in range(values.shape[1])], axis=1) / safe[:, None]

    mean, centre = cell_mean(shift), cell_mean(start)
    offset, deviation = start - centre[cells], shift - mean[cells]
    # per cell: gradient G (2 x 2) of displacement on position, least squares
    products = np.einsum("ni,nj->nij", offset, offset).reshape(-1, 4)
    covariance = cell_mean(products).reshape(-1, 2, 2) + 1e-12 * np.eye(2)
    cross = cell_mean(np.einsum("ni,nj->nij", offset, deviation).reshape(-1, 4)).reshape(-1, 2, 2)
    gradient = np.linalg.solve(covariance, cross)
    residual = deviation - np.einsum("ni,nij->nj", offset, gradient[cells])
    variance = np.bincount(cells, weights=mass * (residual ** 2).sum(axis=1),
                           minlength=grid.n_cells) / safe
    used = count >= MIN_PARTICLES
    diffusivity = variance[used] * count[used] / (count[used] - 3) / (4.0 * tau)
    speed = np.hypot(mean[used, 0], mean[used, 1]) / tau
    weight = total[used]
    return np.array([(weight * diffusivity * speed).sum(), (weight * speed * speed).sum()])


def dispersivity(fits) -> float:
    """alpha [m] from the per-sample sums of ``dispersion_fit`` (S, 2); 0 without flow."""
    sums = np.asarray(fits, dtype=np.float64).reshape(-1, 2).sum(axis=0)
    return float(sums[0] / sums[1]) if sums[1] > 0 else 0.0


@numba.njit(cache=True)
def _disperse(position, field, x0, y0, dx, dy, alpha, seconds, normal, x_lo, x_hi, y_lo):
    for n in range(position.shape[0]):
        u, v = sample(field, x0, y0, dx, dy, position[n, 0], position[n, 1])
        spread = np.sqrt(2.0 * alpha * np.hypot(u, v) * seconds)
        position[n, 0] = min(max(position[n, 0] + spread * normal[n, 0], x_lo), x_hi)
        position[n, 1] = max(position[n, 1] + spread * normal[n, 1], y_lo)


def disperse(position: np.ndarray, field: np.ndarray, grid: Grid, alpha: float, seconds: float,
             rng: np.random.Generator, x_lo: float = -np.inf, x_hi: float = np.inf,
             y_lo: float = -np.inf) -> None:
    """Random-walk step of ``seconds`` [s] in place: D = alpha |v| at each particle;
    positions then kept in x in [x_lo, x_hi], y >= y_lo [m] (the container)."""
    if alpha <= 0 or position.shape[0] == 0:
        return
    normal = rng.standard_normal(position.shape)
    _disperse(position, field, grid.x_min, grid.y_min, grid.dx, grid.dy, float(alpha),
              float(seconds), normal, float(x_lo), float(x_hi), float(y_lo))
