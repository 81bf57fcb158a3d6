"""Emitter: turns incoming material into DEM disks at an inlet.

Rule (every kilogram that enters is in the DEM):

* A lot of ``mass_kg`` without ids is split into ``n = max(1, round(mass /
  m_mean))`` pseudo-particles, ``m_mean`` being the mass of a disk of the
  mean diameter (d_min + d_max) / 2. Their diameters are drawn uniformly in
  [d_min, d_max] with the DEM's seeded generator, and the lot's mass is
  shared in proportion to d^3, so the particle masses sum to ``mass_kg``
  (to rounding) and each one's tracked mass is close to its disk's.
* Particles given with ids (from a ``ParticleStore``) each become one disk.
* A disk's diameter follows from its tracked mass and the density (a sphere),
  clipped to [d_min, d_max]; its *dynamic* mass is always that sphere's
  mass, so the stable time step holds whatever the tracked mass is. The
  tracked mass is what the feeder counts and what the mass balance adds up.
* Disks are laid in rows across the inlet width, each row ``d_max`` above
  the previous, starting one ``d_max`` above the highest disk still in the
  inlet's stream, and start with the inlet's downward velocity.
"""

from __future__ import annotations

import numpy as np

from surrogate.dem.config import DemConfig


def split_lot(cfg: DemConfig, mass_kg: float, rng: np.random.Generator) -> np.ndarray:
    """Tracked masses [kg] of the pseudo-particles of one lot (sum = ``mass_kg``)."""
    mean_mass = mean_particle_mass(cfg)
    count = max(1, int(round(mass_kg / mean_mass)))
    volumes = rng.uniform(cfg.diameter_min ** 3, cfg.diameter_max ** 3, count)
    masses = mass_kg * volumes / volumes.sum()
    # put the rounding residue on the last particle so the sum is mass_kg
    masses[-1] = mass_kg - masses[:-1].sum()
    return masses


def mean_particle_mass(cfg: DemConfig) -> float:
    """Mean pseudo-particle mass [kg]: disk volumes uniform between d_min^3 and d_max^3."""
    return float(0.5 * (cfg.sphere_mass(cfg.diameter_min) + cfg.sphere_mass(cfg.diameter_max)))


def inlet_positions(cfg: DemConfig, inlet: int, radius: np.ndarray, existing_pos: np.ndarray,
                    existing_radius: np.ndarray) -> np.ndarray:
    """Start positions (N, 2) [m] of new disks with ``radius`` at ``inlet``."""
    x0, y0 = cfg.inlets[inlet]
    half = cfg.inlet_width / 2.0
    d_max = cfg.diameter_max
    base = y0
    if existing_pos.shape[0]:
        near = ((np.abs(existing_pos[:, 0] - x0) < half + d_max)
                & (existing_pos[:, 1] > y0 - 2.0 * d_max))
        if near.any():
            base = max(base, float((existing_pos[near, 1] + existing_radius[near]).max()) + d_max / 2)
    per_row = max(1, int(cfg.inlet_width // d_max))
    k = np.arange(radius.size)
    row, col = np.divmod(k, per_row)
    x = x0 - half + d_max / 2 + col * d_max + (row % 2) * 0.25 * d_max
    y = base + d_max / 2 + row * d_max
    return np.column_stack((np.minimum(x, x0 + half), y))
