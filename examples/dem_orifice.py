"""Orifice discharge of the 2D DEM against Beverloo's law: measures the constant C.

Scene (``orifice_bin``): a bunker ``width`` m wide with a raised floor at
``FLOOR_Y`` = 2 m that has an opening of ``b`` m in its middle; disks of the
default sizes (0.2-0.48 m) are laid on a lattice above it and flow out under
gravity; a feeder spanning the floor below takes every disk that fell
through (a sink, far above any capacity). The discharge rate is the mass
taken between ``--skip`` and ``--duration`` seconds, while the bunker is
still more than a third full (Beverloo's rate does not depend on the head).
For each opening and seed it prints the rate and ``C = W / (rho_2D sqrt(g)
(b - k d)^1.5)`` with ``k = 1.5``, ``rho_2D`` and ``d`` from ``DemConfig``
(``areal_bulk_density``, ``mean_diameter``), and the mean and standard
deviation of C over all runs.

Run: ``.venv/bin/python examples/dem_orifice.py`` (about 20 minutes on the
shared 2-core machine; ``--widths``, ``--seeds`` and ``--duration`` make it shorter or longer).
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from cosim import jsonio
from surrogate.dem import Dem, DemConfig
from surrogate.dem.config import GRAVITY

FLOOR_Y = 2.0
"""Height [m] of the raised floor with the opening."""


def orifice_bin(opening: float, seed: int, width: float = 16.0, fill_height: float = 25.0,
                method: str = "explicit", **overrides) -> Dem:
    """A ``Dem`` of the bunker described in the module docstring, at rest
    (``method`` and ``overrides``: ``DemConfig`` fields)."""
    half = width / 2.0
    cfg = DemConfig(**{**dict(
        method=method, floor_width=width, side_wall_height=FLOOR_Y + fill_height + 1.0,
        extra_walls=[[-half, FLOOR_Y, -opening / 2, FLOOR_Y],
                     [opening / 2, FLOOR_Y, half, FLOOR_Y]],
        inlets=[[0.0, FLOOR_Y + fill_height + 0.5]], outlets=[0.0],
        outlet_width=width - 1.0, feeder_zone_height=FLOOR_Y - 0.3,
        max_discharge_rate=1e6), **overrides})
    rng = np.random.default_rng(seed)
    pitch = cfg.diameter_max + 1e-3
    xs = np.arange(-half + pitch / 2, half - pitch / 2, pitch)
    ys = np.arange(FLOOR_Y + pitch / 2, FLOOR_Y + fill_height, pitch)
    grid = np.array([(x, y) for y in ys for x in xs])
    diameters = np.cbrt(rng.uniform(cfg.diameter_min ** 3, cfg.diameter_max ** 3, len(grid)))
    dem = Dem(cfg, seed=seed)
    dem.place(grid, cfg.sphere_mass(diameters), 0.5, 1.0, np.eye(16)[12], 0)
    return dem


def discharge_rate(opening: float, seed: int, skip: float, duration: float) -> dict:
    dem = orifice_bin(opening, seed)
    held = dem.held_mass()
    dem.set_discharge_rate(dem.cfg.max_discharge_rate)
    dem.advance(skip)
    dem.discharged()
    dem.advance(duration - skip)
    out = dem.discharged()["mass"].sum()
    rate = out / (duration - skip)
    cfg = dem.cfg
    beverloo = cfg.areal_bulk_density * math.sqrt(GRAVITY) * max(
        opening - 1.5 * cfg.mean_diameter, 0.0) ** 1.5
    return {"opening_m": opening, "seed": seed, "rate_kg_s": rate, "C": rate / beverloo,
            "held_fraction_end": dem.held_mass() / held}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--widths", default="4.0,5.0",
                        help="openings b [m] (2.5 m and narrower jam: arches of rough disks)")
    parser.add_argument("--seeds", default="0,1", help="seeds of the disk sizes")
    parser.add_argument("--skip", type=float, default=2.0, help="start-up left out [s]")
    parser.add_argument("--duration", type=float, default=6.0, help="simulated time [s]")
    args = parser.parse_args(argv)
    rows = []
    for b in map(float, args.widths.split(",")):
        for seed in map(int, args.seeds.split(",")):
            row = discharge_rate(b, seed, args.skip, args.duration)
            print(jsonio.dumps(row), file=sys.stderr, flush=True)
            rows.append(row)
    c = np.array([r["C"] for r in rows])
    print(jsonio.dumps({"rows": rows, "C_mean": float(c.mean()), "C_sd": float(c.std(ddof=1))
                        if c.size > 1 else 0.0}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
