"""Surface layer: where incoming particles come to rest on the pile.

Source: paper section "Integration test": incoming particles "fall, impact,
and disperse over the pile surface"; Wallin and Servin (2021) keep resolved
DEM for the free particles. We use a simpler documented scheme instead of a
second DEM of the free particles (it runs in microseconds per particle and
needs no contact model): a granular sandpile (avalanche) rule on the pile's
height profile.

Equations:

- The pile surface is a height profile over columns of width w [m]:
  h_c = floor + M_c / (rho_A w), with M_c the bulk mass in column c [kg] and
  rho_A the areal bulk density [kg/m^2] (``Container.areal_density``).
- A particle of mass m falls vertically from the inlet (column of
  ``inlet_x`` plus a uniform jitter of +-1 column, the spread of the falling
  stream) and lands on the surface; or, after a resolved impact
  (``surrogate.rom.surface_dem``), it starts in the column where the DEM
  left it.
- It then rolls downhill: while the drop to a neighbouring column exceeds
  tan(repose_angle) w it moves to the lower neighbour (the steeper side; a
  tie is broken by a uniform draw). This is the angle-of-repose relaxation
  of a cellular sandpile.
- It joins the bulk where it stops: x uniform within the column, y at the
  middle of the slab it adds, and the column rises by m / (rho_A w).
"""

from __future__ import annotations

import numba
import numpy as np

from surrogate.rom.container import Container


PARTICLES_PER_COLUMN = 2.5
"""Column width in particle extents: one particle per column would make the
column heights jump by a whole particle, a local "slope" far above any angle
of repose, and the avalanche rule would then fire on that noise."""


def column_width(container: Container, typical_mass: float) -> float:
    """Column width [m]: ``PARTICLES_PER_COLUMN`` particle extents (sqrt of a
    particle's area in the plane)."""
    return float(PARTICLES_PER_COLUMN * np.sqrt(typical_mass / container.areal_density))


def surface_heights(container: Container, width: float, position, mass) -> np.ndarray:
    """Height h_c [m] of the bulk surface in each column (see module docstring)."""
    columns = max(int(round((container.x_max - container.x_min) / width)), 1)
    width = (container.x_max - container.x_min) / columns
    index = np.clip(((np.asarray(position)[:, 0] - container.x_min) / width).astype(np.int64),
                    0, columns - 1)
    column_mass = np.bincount(index, weights=mass, minlength=columns)
    return container.floor + column_mass / (container.areal_density * width)


@numba.njit(cache=True)
def _deposit(heights, x_min, width, start_column, mass, areal_density, max_drop, tie, offset,
             out):
    columns = heights.size
    for k in range(mass.size):
        c = min(max(start_column[k], 0), columns - 1)
        for _ in range(columns):
            left = heights[c] - heights[c - 1] if c > 0 else -1.0
            right = heights[c] - heights[c + 1] if c < columns - 1 else -1.0
            if max(left, right) <= max_drop:
                break
            if left > right or (left == right and tie[k] < 0.5):
                c -= 1
            else:
                c += 1
        rise = mass[k] / (areal_density * width)
        out[k, 0] = x_min + (c + offset[k]) * width
        out[k, 1] = heights[c] + 0.5 * rise
        heights[c] += rise


def deposit(container: Container, width: float, heights: np.ndarray, mass,
            rng: np.random.Generator, landing_x=None) -> np.ndarray:
    """Resting positions (N, 2) [m] of arriving particles of ``mass``, in order.

    ``heights`` (from ``surface_heights`` with the same ``width``) is updated
    in place as the particles settle. ``landing_x`` [m] (N,) starts each
    particle in the column under it instead of under the inlet.
    """
    mass = np.ascontiguousarray(mass, dtype=np.float64)
    columns = heights.size
    width = (container.x_max - container.x_min) / columns
    draws = rng.random((3, mass.size))
    if landing_x is None:
        inlet_column = int((container.inlet_x - container.x_min) / width)
        start = inlet_column + np.floor(draws[0] * 3.0).astype(np.int64) - 1
    else:
        start = np.floor((np.asarray(landing_x) - container.x_min) / width).astype(np.int64)
    out = np.empty((mass.size, 2))
    _deposit(heights, container.x_min, width, start, mass, container.areal_density,
             np.tan(container.repose_angle) * width, draws[1], draws[2], out)
    return out


@numba.njit(cache=True)
def _sort_into_columns(position, x_min, width, columns, hint, column, order, start):
    """``order``: particle indices by column, then height (ties by index), and
    ``start`` (columns + 1) each column's first entry; ``column`` per particle.

    A counting sort by column in the order of ``hint`` (the previous step's
    stacking order), then an insertion sort by height within each column: one
    step of advection leaves a pile nearly in that order, so this is O(n)
    where a full sort is O(n log n). The result does not depend on the hint.
    """
    n = position.shape[0]
    start[:] = 0
    for p in range(n):
        c = int((position[p, 0] - x_min) / width)
        c = min(max(c, 0), columns - 1)
        column[p] = c
        start[c + 1] += 1
    for c in range(columns):
        start[c + 1] += start[c]
    fill = start[:columns].copy()
    for k in range(n):
        p = hint[k]
        order[fill[column[p]]] = p
        fill[column[p]] += 1
    for c in range(columns):
        for i in range(start[c] + 1, start[c + 1]):
            p = order[i]
            y = position[p, 1]
            j = i - 1
            while j >= start[c] and (position[order[j], 1] > y
                                     or (position[order[j], 1] == y and order[j] > p)):
                order[j + 1] = order[j]
                j -= 1
            order[j + 1] = p


@numba.njit(cache=True)
def _downhill(height, c, max_drop, sweep):
    """The neighbour column the top of column ``c`` slides onto: the lower one where a
    drop exceeds ``max_drop`` (ties alternate side with ``sweep``), else -1."""
    columns = height.size
    left = height[c] - height[c - 1] if c > 0 else -1.0
    right = height[c] - height[c + 1] if c < columns - 1 else -1.0
    if max(left, right) <= max_drop:
        return -1
    if left == right:
        return c - 1 if sweep % 2 == 0 else c + 1
    return c - 1 if left > right else c + 1


@numba.njit(cache=True)
def _column_stacks(position, x_min, width, columns, hint, sweeps):
    """The particles in column and height order (``sorted_``, each one's ``column``) and
    each column's stack (bottom first, ``filled`` deep), with room for ``sweeps``
    avalanches onto any column."""
    n = position.shape[0]
    column = np.empty(n, np.int64)
    sorted_ = np.empty(n, np.int64)
    start = np.empty(columns + 1, np.int64)
    _sort_into_columns(position, x_min, width, columns, hint, column, sorted_, start)
    capacity = (start[1:] - start[:-1]).max() + sweeps + 1
    stack = np.empty((columns, capacity), np.int64)
    filled = np.zeros(columns, np.int64)
    for k in range(n):
        c = column[sorted_[k]]
        stack[c, filled[c]] = sorted_[k]
        filled[c] += 1
    return column, sorted_, stack, filled


@numba.njit(cache=True)
def _avalanches(position, mass, stack, filled, height, floor, column_density, width, max_drop,
                sweeps, on_tops):
    """Up to ``sweeps`` sweeps, alternating direction: the top particle of every column
    more than ``max_drop`` above a neighbour slides onto it (``_downhill``). ``height``:
    each column's packed height (its mass over ``column_density``), or with ``on_tops``
    the real top of its top particle, on which the sliding particle then lands."""
    columns = filled.size
    capacity = stack.shape[1]
    for sweep in range(sweeps):
        moved = False
        for step in range(columns):
            c = step if sweep % 2 == 0 else columns - 1 - step
            if filled[c] == 0:
                continue
            d = _downhill(height, c, max_drop, sweep)
            if d < 0 or filled[d] >= capacity:
                continue
            filled[c] -= 1
            p = stack[c, filled[c]]
            stack[d, filled[d]] = p
            filled[d] += 1
            rise = mass[p] / column_density
            position[p, 0] += (d - c) * width
            if on_tops:
                if filled[c] > 0:
                    below = stack[c, filled[c] - 1]
                    height[c] = position[below, 1] + 0.5 * mass[below] / column_density
                else:
                    height[c] = floor
                position[p, 1] = height[d] + 0.5 * rise
            else:
                height[c] -= rise
            height[d] += rise
            moved = True
        if not moved:
            break


@numba.njit(cache=True)
def _settle(position, mass, x_min, width, columns, floor, areal_density, max_drop, sweeps, hint,
            relax):
    column, sorted_, stack, filled = _column_stacks(position, x_min, width, columns, hint,
                                                    sweeps)
    n = position.shape[0]
    height = np.full(columns, floor)
    for k in range(n):
        p = sorted_[k]
        height[column[p]] += mass[p] / (areal_density * width)
    # angle-of-repose relaxation: the top particle of a too-steep column slides
    # over; sweeps alternate direction and ties alternate side (no drift bias)
    _avalanches(position, mass, stack, filled, height, floor, areal_density * width, width,
                max_drop, sweeps, False)
    # density projection: each column is a packed stack in its particles' height order
    k = 0
    for c in range(columns):
        top = floor
        for i in range(filled[c]):
            p = stack[c, i]
            rise = mass[p] / (areal_density * width)
            if relax == 1.0:
                position[p, 1] = top + 0.5 * rise
            else:
                position[p, 1] += relax * (top + 0.5 * rise - position[p, 1])
            top += rise
            sorted_[k] = p
            k += 1
    return sorted_


def _columns_and_hint(container: Container, width: float, position, hint):
    """The container's column count, their width [m] nearest ``width``, and the
    checked ``hint`` (identity if None) of ``settle`` and ``settle_loose``."""
    columns = max(int(round((container.x_max - container.x_min) / width)), 1)
    width = (container.x_max - container.x_min) / columns
    hint = np.arange(len(position)) if hint is None else np.asarray(hint, dtype=np.int64)
    if hint.size != len(position):
        raise ValueError(f"hint: a permutation of the {len(position)} particles, "
                         f"got {hint.size} entries")
    return columns, width, hint


def settle(container: Container, width: float, position: np.ndarray, mass,
           sweeps: int = 20, hint=None, relax: float = 1.0) -> np.ndarray:
    """Pack the bulk in place: angle-of-repose avalanching, then packed columns.

    The advected field is a regression, not divergence free, so advection
    alone would compact or dilute the bulk. After each advection step every
    column of width w is re-stacked at the bulk density in the height order
    the advection gave its particles (y_n = floor + (sum of the masses below
    + m_n / 2) / (rho_A w)): a column loses height exactly as the feeder
    takes mass from it, which is how the funnel sinks. Before that, up to
    ``sweeps`` times, the top particle of every column steeper than the angle
    of repose against a neighbour slides onto that neighbour (surface
    avalanches into the crater above the funnel).

    With ``relax`` [-] (default 1) below 1 each particle moves only that
    fraction of the way to its packed height: a light packing that, without
    avalanches (``sweeps=0``), keeps every column's height order (the new
    heights are a convex combination of two sequences that rise along it) and
    lets a density error decay over about 1 / relax calls instead of undoing
    it at once.

    Returns the stacking order (particle indices column by column, bottom to
    top). Passed back as ``hint`` at the next call it makes the sort linear in
    the number of particles (the result is the same with any hint).
    """
    if len(position) == 0:
        return np.empty(0, np.int64)
    columns, width, hint = _columns_and_hint(container, width, position, hint)
    return _settle(position, np.ascontiguousarray(mass, dtype=np.float64), container.x_min,
                   width, columns, container.floor, container.areal_density,
                   np.tan(container.repose_angle) * width, int(sweeps), hint, float(relax))


@numba.njit(cache=True)
def _settle_loose(position, mass, x_min, width, columns, floor, areal_density, max_drop, sweeps,
                  hint, void_gap):
    column, sorted_, stack, filled = _column_stacks(position, x_min, width, columns, hint,
                                                    sweeps)
    n = position.shape[0]
    top = np.full(columns, floor)
    # bottom up, each particle falls until it is at most void_gap above the stack below
    for k in range(n):
        p = sorted_[k]
        c = column[p]
        half = 0.5 * mass[p] / (areal_density * width)
        position[p, 1] = min(position[p, 1], top[c] + void_gap + half)
        top[c] = position[p, 1] + half
    # avalanches on the columns' real tops: the top particle of a too-steep column lands
    # on its neighbour's top
    _avalanches(position, mass, stack, filled, top, floor, areal_density * width, width,
                max_drop, sweeps, True)
    k = 0
    for c in range(columns):
        for i in range(filled[c]):
            sorted_[k] = stack[c, i]
            k += 1
    return sorted_


def settle_loose(container: Container, width: float, position: np.ndarray, mass,
                 void_gap: float, sweeps: int = 20, hint=None) -> np.ndarray:
    """Let the bulk rest on its base without compacting it: voids close, the field's
    spacing stays.

    Cohesionless rock cannot stand over a void (``surrogate.rom.hanging``), but a
    fitted field also spaces its bulk as the DEM's flow does, dilating the funnel;
    ``settle`` re-stacks every column at the bulk density and undoes that. Here,
    column by column from the bottom (columns of width w, the particles in their
    height order), a particle whose lower edge is more than ``void_gap`` [m] above
    the top of the stack below it falls to that gap (y_n <= top_{n-1} + void_gap +
    h_n / 2, h_n = m_n / (rho_A w) its slab, top_n = y_n + h_n / 2); no particle
    rises. Then, up to ``sweeps`` times, the top particle of every column whose
    real top stands more than tan(repose_angle) w above a neighbour's slides onto
    that neighbour's top (``settle``'s avalanches, on the stacks as they stand).

    Returns the stacking order, as ``settle`` does (``hint``: the previous one).
    """
    if len(position) == 0:
        return np.empty(0, np.int64)
    columns, width, hint = _columns_and_hint(container, width, position, hint)
    return _settle_loose(position, np.ascontiguousarray(mass, dtype=np.float64),
                         container.x_min, width, columns, container.floor,
                         container.areal_density, np.tan(container.repose_angle) * width,
                         int(sweeps), hint, float(void_gap))


@numba.njit(cache=True)
def _feeder_take(position, mass, lo, hi, top, x_min, width, drained, weight, credit, out):
    columns = drained.size
    n = position.shape[0]
    # the particles in the feeder's zone, found once (the rest cannot be taken)
    zone = np.empty(n, np.int64)
    zone_size = 0
    for p in range(n):
        x, y = position[p, 0], position[p, 1]
        if lo <= x <= hi and y <= top:
            zone[zone_size] = p
            zone_size += 1
    taken = np.zeros(zone_size, np.bool_)
    count = 0
    while True:
        # the lowest untaken particle of every column over the opening
        best = np.full(columns, -1, np.int64)
        for k in range(zone_size):
            if taken[k]:
                continue
            p = zone[k]
            c = min(max(int((position[p, 0] - x_min) / width), 0), columns - 1)
            if best[c] < 0 or position[p, 1] < position[zone[best[c]], 1]:
                best[c] = k
        # the column least drained for its weight gives its lowest particle
        pick = -1
        for c in range(columns):
            if best[c] >= 0 and weight[c] > 0 and (
                    pick < 0 or drained[c] * weight[pick] < drained[pick] * weight[c]):
                pick = c
        if pick < 0 or mass[zone[best[pick]]] > credit:
            return count, credit
        p = zone[best[pick]]
        credit -= mass[p]
        drained[pick] += mass[p]
        taken[best[pick]] = True
        out[count] = p
        count += 1


def feeder_take(container: Container, width: float, position, mass, drained: np.ndarray,
                credit: float, weight=None):
    """Particles the belt feeder takes with ``credit`` [kg]: ``(indices, credit left)``.

    The feeder draws across its opening (outlet_x +- outlet_width / 2, up to
    ``feeder_zone_height`` above the floor) in proportion to ``weight``
    (columns,) [any unit, >= 0] per packing column (default: evenly): of the
    columns over the opening, the one with the least mass given so far for
    its weight (``drained`` [kg] per column, updated in place) gives its
    lowest particle, while the credit covers that particle's mass; a column
    of weight 0 gives nothing. (Taking simply the lowest particle in the
    zone, as the DEM's feeder does, would drain one packing column at a
    time: a rat hole the DEM's contacts do not allow.) ``RomStorage`` weighs
    the columns by the predicted field's downward speed over the feeder.
    """
    lo = container.outlet_x - 0.5 * container.outlet_width
    hi = container.outlet_x + 0.5 * container.outlet_width
    columns = drained.size
    width = (container.x_max - container.x_min) / columns
    weight = (np.ones(columns) if weight is None
              else np.ascontiguousarray(weight, dtype=np.float64).reshape(columns))
    out = np.empty(len(mass), np.int64)
    count, credit = _feeder_take(position, np.ascontiguousarray(mass, dtype=np.float64), lo, hi,
                                 container.floor + container.feeder_zone_height,
                                 container.x_min, width, drained, weight, float(credit), out)
    return out[:count], credit
