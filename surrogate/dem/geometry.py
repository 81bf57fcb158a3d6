"""Static geometry of the 2D stockpile: wall segments, feeder zones, inlets.

The floor is one segment at y = 0 from -floor_width/2 to +floor_width/2;
each outlet is a belt feeder flush with the floor (so the floor segment also
covers it) that draws disks from the zone above it (see
``kernels.run_steps``); vertical side walls of ``side_wall_height`` stand at
both floor ends.
"""

from __future__ import annotations

import numpy as np

from surrogate.dem.config import DemConfig


def wall_segments(cfg: DemConfig) -> np.ndarray:
    """Rows ``(ax, ay, bx, by)`` [m]: floor, left wall, right wall, extra walls."""
    half = cfg.floor_width / 2.0
    height = cfg.side_wall_height
    walls = [[-half, 0.0, half, 0.0], [-half, 0.0, -half, height], [half, 0.0, half, height]]
    return np.array(walls + list(cfg.extra_walls), dtype=np.float64)


def feeder_zones(cfg: DemConfig):
    """``(lo, hi, top)``: x bounds [m] of each outlet's zone and its top y [m]."""
    centres = np.asarray(cfg.outlets, dtype=np.float64)
    half = cfg.outlet_width / 2.0
    return centres - half, centres + half, float(cfg.feeder_zone_height)
