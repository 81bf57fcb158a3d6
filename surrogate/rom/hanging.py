"""Bulk hanging over emptied cells: a check of the pile's shape, not of its outflow.

Cohesionless rock (the training DEM's ``cohesion`` is 0) cannot rest over a void:
under gravity a cell of bulk whose cell directly below has emptied falls into it.
The DEM's piles show almost none: at most 0.0014 of the mass in any of the 1,164
sampled fields of the paper design, 0.0007 in the validation scene's 352, 0.0022 in
the draining validation scene's and 0.0027 in the held-out scenes' 1,584 (9 replicas
of 176; 0 at the end of every replica of every scene), the moment's bounce of rock
landing on the bulk. A ROM that moves its bulk only by its fitted
field, with no packing (``RomStorage(packing="none")``), can leave bulk behind where
its field is slow while the cells under it drain; the tracking error, which scores
only the order of what leaves, does not see it.

Definition, on a mass field (ny, nx) [kg] on the model grid (row 0 at the floor):
the **hanging share** is the mass in cells, above the bottom row, whose cell
directly below holds less than ``EMPTY_FILL`` of a full cell (rho_A dx dy, rho_A
the container's areal density), over the field's whole mass [-].
"""

from __future__ import annotations

import numpy as np

from surrogate.rom.container import Container
from surrogate.rom.grid import Grid, mass_field

EMPTY_FILL = 0.1
"""Fill [-] (of rho_A dx dy) under which a cell counts as emptied."""

HANGING_LIMIT = 0.005
"""Largest hanging share [-] a pile may show and still count as resting on its base:
about twice the DEM's largest (0.0027, module docstring). On the paper's pile states
the shipped fixed-grid ROM shows 0; the registered option, without packing, 0.014 on
the depleted state (surrogate/rom/README.md, "The pile the option builds")."""


def hanging_share(mass: np.ndarray, grid: Grid, container: Container,
                  empty_fill: float = EMPTY_FILL) -> float:
    """Hanging share [-] (module docstring) of the mass field ``mass`` (ny, nx) [kg];
    0 for an empty field."""
    mass = np.asarray(mass, dtype=np.float64)
    if mass.shape != grid.shape:
        raise ValueError(f"mass field of shape {mass.shape}, the grid's is {grid.shape}")
    total = float(mass.sum())
    if total <= 0.0:
        return 0.0
    emptied_below = mass[:-1] < empty_fill * container.full_cell_mass(grid)
    return float(mass[1:][emptied_below].sum() / total)


def hanging_share_of(position: np.ndarray, mass: np.ndarray, grid: Grid,
                     container: Container) -> float:
    """Hanging share [-] of particles at ``position`` (N, 2) [m] of ``mass`` (N,) [kg]."""
    return hanging_share(mass_field(grid, position, mass), grid, container)
