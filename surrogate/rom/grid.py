"""Eulerian fields on a regular grid from particle snapshots.

Source: Wallin and Servin (2021), as used in the paper's section "Digital twin
as a distributed particle simulation": the reduced-order model maps the mass
distribution of the stockpile, sampled on a fixed grid, to the velocity field
on the same grid. The pile is the DEM's vertical plane: x horizontal [m],
y vertical (up) [m].

Fields (all cell arrays have shape ``(ny, nx)``; row j is height y_j):

- mass per cell M_c = sum_{n in c} m_n [kg];
- a mass-weighted mean of any particle attribute a_c = sum m_n a_n / M_c
  (grade, hardness; NaN in empty cells);
- velocity per cell v_c [m/s], shape ``(ny, nx, 2)``: the mass-weighted mean
  displacement velocity (x_n(t+T) - x_n(t)) / T of the particles present in
  both snapshots, binned at their mid-point. The displacement velocity over T
  (default 1 s) rather than the instantaneous DEM velocity is used because it
  is what advection over steps of that size needs (contact rattling averages
  out). Empty cells have zero velocity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosim.errors import ValidationError


@dataclass(frozen=True)
class Grid:
    """Regular grid over the rectangle [x_min, x_max] x [y_min, y_max] [m].

    Parameters
    ----------
    x_min, x_max, y_min, y_max : float
        Extent [m].
    nx, ny : int
        Cells along x and y (cell size a few particle diameters).
    """

    x_min: float
    x_max: float
    y_min: float
    y_max: float
    nx: int
    ny: int

    def __post_init__(self):
        if not (self.x_max > self.x_min and self.y_max > self.y_min):
            raise ValidationError("grid", "an extent with x_max > x_min and y_max > y_min",
                                  f"got {self.to_dict()}")
        if self.nx < 1 or self.ny < 1:
            raise ValidationError("grid", "nx >= 1 and ny >= 1", f"got {self.nx}, {self.ny}")

    @classmethod
    def covering(cls, x_min, x_max, y_min, y_max, cell_size) -> "Grid":
        """Grid of about ``cell_size`` [m] square cells covering the rectangle."""
        nx = max(int(round((x_max - x_min) / cell_size)), 1)
        ny = max(int(round((y_max - y_min) / cell_size)), 1)
        return cls(float(x_min), float(x_max), float(y_min), float(y_max), nx, ny)

    @property
    def dx(self) -> float:
        return (self.x_max - self.x_min) / self.nx

    @property
    def dy(self) -> float:
        return (self.y_max - self.y_min) / self.ny

    @property
    def n_cells(self) -> int:
        return self.nx * self.ny

    @property
    def shape(self) -> tuple[int, int]:
        return (self.ny, self.nx)

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates ``(x (nx,), y (ny,))`` [m]."""
        x = self.x_min + (np.arange(self.nx) + 0.5) * self.dx
        y = self.y_min + (np.arange(self.ny) + 0.5) * self.dy
        return x, y

    def cell_index(self, position) -> np.ndarray:
        """Flat cell index (row-major, ``j * nx + i``) of each position; -1 outside."""
        position = np.asarray(position, dtype=np.float64)
        i = np.floor((position[:, 0] - self.x_min) / self.dx).astype(np.int64)
        j = np.floor((position[:, 1] - self.y_min) / self.dy).astype(np.int64)
        inside = (i >= 0) & (i < self.nx) & (j >= 0) & (j < self.ny)
        return np.where(inside, j * self.nx + i, -1)

    def to_dict(self) -> dict:
        return {"x_min": self.x_min, "x_max": self.x_max, "y_min": self.y_min,
                "y_max": self.y_max, "nx": self.nx, "ny": self.ny}

    @classmethod
    def from_dict(cls, data: dict) -> "Grid":
        return cls(float(data["x_min"]), float(data["x_max"]), float(data["y_min"]),
                   float(data["y_max"]), int(data["nx"]), int(data["ny"]))


def mass_field(grid: Grid, position, mass) -> np.ndarray:
    """Mass per cell [kg], shape ``(ny, nx)``; particles outside the grid are ignored."""
    cells = grid.cell_index(position)
    inside = cells >= 0
    return np.bincount(cells[inside], weights=np.asarray(mass, dtype=np.float64)[inside],
                       minlength=grid.n_cells).reshape(grid.shape)


def mean_field(grid: Grid, position, mass, values) -> np.ndarray:
    """Mass-weighted mean of ``values`` per cell, shape ``(ny, nx)``; NaN where empty."""
    cells = grid.cell_index(position)
    inside = cells >= 0
    mass = np.asarray(mass, dtype=np.float64)[inside]
    total = np.bincount(cells[inside], weights=mass, minlength=grid.n_cells)
    weighted = np.bincount(cells[inside], weights=mass * np.asarray(values)[inside],
                           minlength=grid.n_cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(total > 0, weighted / np.where(total > 0, total, 1.0), np.nan)
    return mean.reshape(grid.shape)


def displacement_velocity_field(grid: Grid, before: dict, after: dict) -> np.ndarray:
    """Velocity per cell [m/s], ``(ny, nx, 2)``, from two snapshots' displacements.

    ``before`` and ``after`` are DEM snapshot dicts (``time``, ``id``,
    ``position`` (N, 2), ``mass``). Particles present in both are binned at
    their mid-point; the cell value is their mass-weighted mean velocity.
    """
    span = float(after["time"]) - float(before["time"])
    if span <= 0:
        raise ValidationError("after.time", f"> before.time = {before['time']!r}",
                              f"got {after['time']!r}")
    common, ia, ib = np.intersect1d(before["id"], after["id"], assume_unique=True,
                                    return_indices=True)
    start = np.asarray(before["position"])[ia]
    end = np.asarray(after["position"])[ib]
    velocity = (end - start) / span
    mid = 0.5 * (start + end)
    mass = np.asarray(before["mass"])[ia]
    cells = grid.cell_index(mid)
    inside = cells >= 0
    total = np.bincount(cells[inside], weights=mass[inside], minlength=grid.n_cells)
    field = np.zeros((grid.n_cells, 2))
    safe = np.where(total > 0, total, 1.0)
    for axis in range(2):
        field[:, axis] = np.bincount(cells[inside], weights=(mass * velocity[:, axis])[inside],
                                     minlength=grid.n_cells) / safe
    return field.reshape(grid.ny, grid.nx, 2)
