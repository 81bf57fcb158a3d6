"""Height-following coordinates for a pile's velocity fields (registration before the POD).

Source: the terrain-following "sigma" coordinate of numerical weather
prediction (Phillips 1957, "A coordinate system having some special
advantages for numerical forecasting", J. Meteorol. 14, 184-185), used here
to register the velocity snapshots before their proper orthogonal
decomposition, as the shifted POD registers moving features before the
decomposition (Reiss, Schulze, Sesterhenn and Mehrmann 2018, "The shifted
proper orthogonal decomposition: a mode decomposition for multiple transport
phenomena", SIAM J. Sci. Comput. 40, A1322-A1344).

Why: on the fixed grid the funnel's narrow core, the resting flanks and the
surface flows sit at other cells for every pile shape, so a POD of the
design's fields needs hundreds of modes to carry what tracking needs
(surrogate/rom/README.md, "What the fit can reach"). Measured from the floor
in units of each column's own height, they sit at about the same place.

Equations (2-D plane, x horizontal, y up from the grid's bottom y_min):

- Column height H_i = sum_j M_ji / (rho_A dx) [m]: the column's mass
  (``mass`` (ny, nx) [kg]) stacked at the areal density rho_A [kg/m^2]
  (``areal_density``) the mass field was packed at.
- Registered coordinate eta = (y - y_min) / H_i in (0, 1); ``levels`` levels
  at eta_k = (k + 1/2) / levels.
- ``register``: the registered field at (eta_k, i) is the column's velocity
  at y = y_min + eta_k H_i, linear between the cell centres (the end cells'
  values beyond them).
- ``unregister``: a cell (j, i) whose centre y_j lies under the column's top
  (y_j - y_min < H_i) takes the registered column at eta = (y_j - y_min) / H_i,
  linear between levels (the end levels' values beyond them); cells above it
  get 0.
- A column lower than half a cell (H_i <= dy / 2) is empty: 0 both ways.

Parameters: ``areal_density`` [kg/m^2] (no default: the density the mass
field is packed at), ``levels`` [-] (default: the grid's ``ny``).
"""

from __future__ import annotations

import numpy as np


def column_heights(mass, grid, areal_density: float) -> np.ndarray:
    """Height [m] of each column, ``(..., nx)``, of ``mass`` ``(..., ny, nx)`` [kg]
    stacked at ``areal_density`` [kg/m^2]."""
    return np.asarray(mass, dtype=np.float64).sum(axis=-2) / (areal_density * grid.dx)


def _along_columns(values: np.ndarray, position: np.ndarray) -> np.ndarray:
    """``values`` (S, n, nx, 2) sampled at fractional row ``position`` (S, m, nx)
    (0 the first row's centre), linear between rows and clamped to the ends."""
    n = values.shape[1]
    position = np.clip(position, 0.0, n - 1)
    lower = np.minimum(np.floor(position).astype(np.int64), max(n - 2, 0))
    weight = (position - lower)[..., None]
    upper = np.minimum(lower + 1, n - 1)
    below = np.take_along_axis(values, lower[..., None], axis=1)
    above = np.take_along_axis(values, upper[..., None], axis=1)
    return (1.0 - weight) * below + weight * above


def register(velocity, mass, grid, areal_density: float, levels: int | None = None) -> np.ndarray:
    """``velocity`` (S, ny, nx, 2) [m/s] of the mass fields ``mass`` (S, ny, nx)
    [kg] on ``levels`` height-following levels: (S, levels, nx, 2) (module
    docstring)."""
    velocity = np.asarray(velocity, dtype=np.float64)
    levels = grid.ny if levels is None else int(levels)
    height = column_heights(mass, grid, areal_density)[:, None, :]  # (S, 1, nx)
    eta = ((np.arange(levels) + 0.5) / levels)[None, :, None]
    position = eta * height / grid.dy - 0.5
    out = _along_columns(velocity, position)
    return np.where((height > 0.5 * grid.dy)[..., None], out, 0.0)


def unregister(registered, mass, grid, areal_density: float) -> np.ndarray:
    """The registered fields ``registered`` (S, levels, nx, 2) [m/s] back on the
    grid of the mass fields ``mass`` (S, ny, nx) [kg]: (S, ny, nx, 2) (module
    docstring)."""
    registered = np.asarray(registered, dtype=np.float64)
    levels = registered.shape[1]
    height = column_heights(mass, grid, areal_density)[:, None, :]  # (S, 1, nx)
    centre = ((np.arange(grid.ny) + 0.5) * grid.dy)[None, :, None]
    safe = np.where(height > 0.0, height, 1.0)
    position = centre / safe * levels - 0.5
    out = _along_columns(registered, position)
    inside = (centre < height) & (height > 0.5 * grid.dy)
    return np.where(inside[..., None], out, 0.0)
