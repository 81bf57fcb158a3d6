"""The DEM's settled bulk density, measured on a training design.

The ROM packs its bulk at one areal density rho_A [kg/m^2]: the container's
``areal_density``, which ``doe.areal_density`` takes as the 90th percentile of the
base pile's cell masses, i.e. nearly a full cell. The DEM's bulk holds less on
average. This module measures the mean the DEM's settled bulk cells hold, so the
ROM can pack at it (``RomStorage(packing_density=...)``).

Definition (per sampled mass field of every run of the design, on the model grid):
a **settled bulk cell** is a cell holding mass whose cell directly above is at
least half full (>= ``ABOVE_FILL`` rho_A dx dy, rho_A the container's density):
the cell is covered by the pile, so it is not the free-surface cell, whose fill
only says where the surface cuts it; the cells of the bottom row over the feeder's
opening (``model.feeder_cells``) are left out, since the belt's draw dilates them
(0.65-0.71 of a full cell in the paper design) and the ROM's feeder takes
particles there by its own rule. Flowing cells elsewhere (the funnel) are kept:
the ROM packs its whole bulk at the one density, so the pile's height and the
mass fields the regression sees follow the mean over all the covered bulk.

The density is the mean mass of those cells over dx dy; per run (all its samples
pooled), then over the runs (each run weighing the same) with its spread.
Source: the design's own data (``doe.load_samples`` layout); no model.

Run: ``python -m surrogate.rom.packing --data surrogate/rom/data/paper_design``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cosim import jsonio
from surrogate.rom import doe
from surrogate.rom.container import Container
from surrogate.rom.grid import Grid
from surrogate.rom.model import feeder_cells

ABOVE_FILL = 0.5
"""Least fill of the cell above [-] (of rho_A dx dy) that makes a cell settled bulk."""


def settled_cells(mass: np.ndarray, grid: Grid, container: Container) -> np.ndarray:
    """Mask (S, ny, nx) of the settled bulk cells of mass fields ``mass`` (S, ny, nx)
    [kg] (module docstring)."""
    mass = np.asarray(mass, dtype=np.float64)
    full = container.full_cell_mass(grid)
    covered = np.zeros(mass.shape, dtype=bool)
    covered[:, :-1] = mass[:, 1:] >= ABOVE_FILL * full
    return covered & (mass > 0) & ~feeder_cells(grid, container)[None]


def settled_density(directory) -> dict:
    """The DEM's mean settled bulk density on the design in ``directory``
    (``train/*.npz``, ``doe.json``): ``density`` [kg/m^2] (mean over runs),
    ``fraction`` of the container's ``areal_density`` [-], their spread over runs
    (``min``, ``max``, ``std``), ``pooled`` (all cells of all runs),
    ``per_run`` {run: [density, cells]}, ``container_density`` [kg/m^2]."""
    grid, container = doe.grid_and_container(directory)
    area = grid.dx * grid.dy
    per_run, total_mass, total_cells = {}, 0.0, 0
    for path in sorted(Path(directory, "train").glob("*.npz")):
        with np.load(path) as data:
            mass = np.asarray(data["mass"], dtype=np.float64)
        cells = settled_cells(mass, grid, container)
        count = int(cells.sum())
        if count == 0:
            continue
        held = float(mass[cells].sum())
        per_run[path.stem] = [held / (count * area), count]
        total_mass, total_cells = total_mass + held, total_cells + count
    values = np.array([v[0] for v in per_run.values()])
    rho = container.areal_density
    return {"density": float(values.mean()), "fraction": float(values.mean() / rho),
            "min": float(values.min()), "max": float(values.max()),
            "std": float(values.std(ddof=1)) if values.size > 1 else 0.0,
            "pooled": total_mass / (total_cells * area), "runs": int(values.size),
            "per_run": per_run, "container_density": rho, "above_fill": ABOVE_FILL}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="training design folder")
    parser.add_argument("--out", help="JSON file to write the measurement to")
    args = parser.parse_args(argv)
    result = settled_density(args.data)
    for run, (density, cells) in result["per_run"].items():
        print(f"{run:28s} {density:8.2f} kg/m^2  {density / result['container_density']:.4f}"
              f"  ({cells} cells)")
    print(f"mean over {result['runs']} runs: {result['density']:.2f} kg/m^2 = "
          f"{result['fraction']:.4f} of {result['container_density']:.2f} (runs "
          f"{result['min']:.2f}-{result['max']:.2f}, sd {result['std']:.2f}; pooled "
          f"{result['pooled']:.2f})")
    if args.out:
        jsonio.write(args.out, result, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
