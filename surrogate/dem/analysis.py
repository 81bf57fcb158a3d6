"""Bulk read-outs of a DEM pile: surface profile and angle of repose.

Angle of repose: the free surface is the highest disk top ``y + r`` in
vertical bins of width ``bin_width`` (default: the largest diameter). On each
side of the highest bin, a straight line is fitted by least squares to the
surface between ``low`` and ``high`` times the pile height (default 20 % and
80 %, skipping the rounded crest and the toe); the angle of repose is the
mean of the two sides' slope angles (a side with fewer than 3 bins in range
is skipped).
"""

from __future__ import annotations

import math

import numpy as np


def surface_profile(pos: np.ndarray, radius: np.ndarray, bin_width: float):
    """``(x_centres, top)`` [m]: the pile's top surface per bin (NaN where empty)."""
    if pos.shape[0] == 0:
        return np.empty(0), np.empty(0)
    x = pos[:, 0]
    lo = x.min()
    k = ((x - lo) / bin_width).astype(np.int64)
    top = np.full(k.max() + 1, np.nan)
    heights = pos[:, 1] + radius
    order = np.argsort(heights)
    top[k[order]] = heights[order]  # the highest disk of a bin is written last
    return lo + (np.arange(top.size) + 0.5) * bin_width, top


def side_angles(pos: np.ndarray, radius: np.ndarray, bin_width: float | None = None,
                low: float = 0.2, high: float = 0.8):
    """Slope angles [deg] of the left and right flanks (NaN if not measurable)."""
    if bin_width is None:
        bin_width = 2.0 * float(radius.max()) if radius.size else 1.0
    xc, top = surface_profile(pos, radius, bin_width)
    if xc.size < 3 or np.all(np.isnan(top)):
        return math.nan, math.nan
    filled = np.nan_to_num(top, nan=0.0)
    peak = int(np.argmax(filled))
    height = filled[peak]
    angles = []
    for side in (slice(0, peak + 1), slice(peak, xc.size)):
        xs, ys = xc[side], filled[side]
        use = (ys >= low * height) & (ys <= high * height)
        if use.sum() < 3:
            angles.append(math.nan)
            continue
        slope = np.polyfit(xs[use], ys[use], 1)[0]
        angles.append(math.degrees(math.atan(abs(slope))))
    return angles[0], angles[1]


def angle_of_repose(pos: np.ndarray, radius: np.ndarray, bin_width: float | None = None) -> float:
    """Mean flank angle [deg] of the pile (NaN if neither flank is measurable)."""
    left, right = side_angles(pos, radius, bin_width)
    both = [a for a in (left, right) if not math.isnan(a)]
    return float(np.mean(both)) if both else math.nan
