"""Hand a ROM pile over to the DEM (the fidelity ladder's fall-back).

Source: issue 10 ("inputs outside the ROM's training ranges give a warning
[...] and the asset can fall back to DEM") and paper section "Digital twin
as a distributed particle simulation" (resolved DEM where the surrogate is
not valid).

The ROM packs its bulk column by column at the DEM's bulk density without
disk geometry, so two particles of one column may overlap as disks. Put into
the DEM at exactly those positions, a deep overlap acts as a compressed
spring (k = 8e6 N/m on a ~100 kg disk: tens of m/s) and throws disks off the
pile. ``drop_heights`` therefore keeps every particle's horizontal position
and the pile's layering (particles are dropped lowest first) and lifts each
disk to the lowest height where it touches, but does not overlap, the disks
below it or the floor:

    y_k = max(floor + r_k, max_j { y_j + sqrt((r_k + r_j)^2 - (x_k - x_j)^2) })

over the already dropped disks j with |x_k - x_j| < r_k + r_j. The DEM then
settles this loose packing under gravity from rest.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def _drop(x, radius, order, floor, x0, bin_width, bins, out_y):
    head = np.full(bins, -1, np.int64)
    following = np.full(x.size, -1, np.int64)
    for k in order:
        r = radius[k]
        y = floor + r
        b = min(max(int((x[k] - x0) / bin_width), 0), bins - 1)
        for nb in range(max(b - 1, 0), min(b + 2, bins)):
            j = head[nb]
            while j >= 0:
                dx = x[k] - x[j]
                reach = r + radius[j]
                if abs(dx) < reach:
                    top = out_y[j] + np.sqrt(reach * reach - dx * dx)
                    if top > y:
                        y = top
                j = following[j]
        out_y[k] = y
        following[k] = head[b]
        head[b] = k


def drop_heights(position, radius, floor: float, x_min: float, x_max: float) -> np.ndarray:
    """Overlap-free positions (N, 2) [m] for disks of ``radius`` [m] (module docstring).

    x is kept (moved inside [x_min + r, x_max - r] if needed); the drop order
    is the ROM height order, so the layering of the pile is kept.
    """
    position = np.asarray(position, dtype=np.float64)
    radius = np.ascontiguousarray(radius, dtype=np.float64)
    out = np.empty_like(position)
    if len(position) == 0:
        return out
    out[:, 0] = np.clip(position[:, 0], x_min + radius, x_max - radius)
    # bins at least one disk diameter wide: only neighbouring bins can touch
    bin_width = max(2.0 * float(radius.max()), 1e-9)
    bins = max(int(np.ceil((x_max - x_min) / bin_width)), 1)
    order = np.argsort(position[:, 1], kind="stable")
    y = np.empty(len(position))
    _drop(np.ascontiguousarray(out[:, 0]), radius, order, float(floor), float(x_min),
          bin_width, bins, y)
    out[:, 1] = y
    return out
