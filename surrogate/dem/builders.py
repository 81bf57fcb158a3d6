"""Ways to build a pile: pour it from the inlets, or lay it out and let it settle.

``config_for_particles(n)`` sizes the geometry for ``n`` particles: a 2D
pile at angle alpha holding area ``A = n * a / phi`` (mean disk area ``a``,
packing fraction phi = 0.82) has height ``H = sqrt(A tan alpha)``; the
inlets are put ``inlet_clearance`` above H and the floor is made 1.5 times
the base width ``2 H / tan alpha`` (at least 20 m), never more than asked.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from cosim.numerics import cbrt
from surrogate.dem.config import PACKING_FRACTION, DemConfig
from surrogate.dem.emitter import mean_particle_mass
from surrogate.dem.simulation import Dem


def pile_height(cfg: DemConfig, n: int, angle_deg: float = 35.0) -> float:
    """Height [m] of a triangular 2D pile of ``n`` disks at ``angle_deg``."""
    # mean disk area when volumes are uniform in [d_min^3, d_max^3]: E[d^2] = (3/5)
    # (d_max^5 - d_min^5) / (d_max^3 - d_min^3)
    lo, hi = cfg.diameter_min, cfg.diameter_max
    mean_area = math.pi / 4.0 * 0.6 * (hi ** 5 - lo ** 5) / (hi ** 3 - lo ** 3)
    area = n * mean_area / PACKING_FRACTION
    return math.sqrt(area * math.tan(math.radians(angle_deg)))


def config_for_particles(n: int, base: DemConfig | None = None, inlet_clearance: float = 2.0,
                         angle_deg: float = 30.0) -> DemConfig:
    """``base`` (default ``DemConfig()``) with inlets and floor sized for ``n`` disks."""
    base = base if base is not None else DemConfig()
    height = pile_height(base, n, angle_deg)
    width = max(20.0, 1.5 * 2.0 * height / math.tan(math.radians(angle_deg)))
    width = min(width, base.floor_width)
    inlet_y = height + inlet_clearance
    inlets = [[x, inlet_y] for x, _ in base.inlets]
    return dataclasses.replace(base, floor_width=width, inlets=inlets)


def pour_pile(dem: Dem, n_particles: int, lot_kg: float = 600.0, lot_interval: float = 0.5,
              grade=None, hardness: float = 1.0, f16=None, progress=None) -> None:
    """Feed lots of ``lot_kg`` [kg] every ``lot_interval`` [s], alternating the
    inlets, until ``n_particles`` disks have entered. Lot k gets tracking id k
    and (by default) a grade that rises linearly from 0.2 to 0.8 over the
    fill, so pictures show the layering. ``progress(dem)`` is called per lot."""
    if f16 is None:
        f16 = np.zeros(16)
        f16[12] = 1.0
    expected_lots = max(1, int(math.ceil(n_particles * mean_particle_mass(dem.cfg) / lot_kg)))
    lot = 0
    entered = 0
    while entered < n_particles:
        g = (0.2 + 0.6 * lot / max(expected_lots - 1, 1)) if grade is None else grade
        remaining = n_particles - entered
        mass = min(lot_kg, remaining * mean_particle_mass(dem.cfg))
        ids = dem.emit(mass, min(g, 1.0), hardness, f16, lot, inlet=lot % len(dem.cfg.inlets))
        entered += ids.size
        lot += 1
        dem.advance(lot_interval)
        if progress is not None:
            progress(dem)


def settle(dem: Dem, max_time: float = 20.0, speed: float = 0.05, chunk: float = 0.5,
           progress=None) -> float:
    """Advance until every disk is slower than ``speed`` [m/s] or ``max_time``
    [s] has passed; returns the time spent settling [s]."""
    start = dem.time
    while dem.time - start < max_time:
        dem.advance(chunk)
        if progress is not None:
            progress(dem)
        if dem.n == 0 or float(np.hypot(dem.vel[:, 0], dem.vel[:, 1]).max()) < speed:
            break
    return dem.time - start


def packed_pile(cfg: DemConfig, n_particles: int, seed: int = 0, angle_deg: float = 35.0) -> Dem:
    """A ``Dem`` with ``n_particles`` disks at rest laid out in a triangle at
    ``angle_deg`` centred on x = 0, to be settled with ``settle``.

    Rows are ``diameter_max`` apart (no vertical overlaps); within a row the
    disks touch side by side (1 mm gaps), so the layout is dense
    horizontally and collapses by about a quarter of its height when it
    settles (to roughly the angle of repose). Disk volumes are uniform
    between those of the smallest and largest diameter (mean mass 84 kg at
    the default density, so 20,000 disks hold 1.7 kt); masses are the disks' sphere masses; grade rises with
    height (0.2 at the floor to 0.8 at the top); tracking ids group 10
    particles. Refused if the pile's base would not fit on the floor.
    """
    rng = np.random.default_rng(seed)
    gap = 1e-3
    row_pitch = cfg.diameter_max + gap
    slope = math.tan(math.radians(angle_deg))
    diameters = cbrt(rng.uniform(cfg.diameter_min ** 3, cfg.diameter_max ** 3, n_particles))
    height = pile_height(cfg, n_particles, angle_deg)
    while True:
        xs, ys, used = [], [], 0
        y = cfg.diameter_max / 2 + gap
        while y < height and used < n_particles:
            half = (height - y) / slope
            d = diameters[used:]
            right_edge = np.cumsum(d + gap)  # right edge of each disk from the row start
            fits = int(np.searchsorted(right_edge, 2.0 * half, side="right"))
            if fits:
                centres = -half + right_edge[:fits] - d[:fits] / 2 - gap
                xs.append(centres)
                ys.append(np.full(fits, y))
                used += fits
            y += row_pitch
        if used >= n_particles:
            break
        height *= 1.03
    pos = np.column_stack((np.concatenate(xs), np.concatenate(ys)))[:n_particles]
    half_base = height / slope
    if half_base > cfg.floor_width / 2 - cfg.diameter_max:
        from cosim.errors import ValidationError

        raise ValidationError("floor_width", f">= {2 * (half_base + cfg.diameter_max):.1f} m "
                              f"for a packed pile of {n_particles} particles",
                              f"got {cfg.floor_width:g} m")
    dem = Dem(cfg, seed=seed)
    f16 = np.zeros(16)
    f16[12] = 1.0
    grade = 0.2 + 0.6 * pos[:, 1] / max(pos[:, 1].max(), 1e-9)
    dem.place(pos, cfg.sphere_mass(diameters), grade, 1.0, f16, np.arange(n_particles) // 10)
    return dem
