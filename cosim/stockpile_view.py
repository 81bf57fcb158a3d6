"""What a storage asset shows: totals, spatial fields, a particle table, the predicted
feed and the display layout, for any bound storage model (``cosim.storage``).

Source: paper section "Integration test": the monitoring service receives the
stockpile's "virtual sensor information": the total mass in the storage, the
average grade, the spatial distributions of these quantities and the
predicted velocity field in the bulk of the pile; section "Predicting the
properties of the mill feed" for the feed. Every average is mass-weighted over
the particles held (the paper's eq. (observation)).

Plain functions of a storage model bound to its ``ParticleStore``: the mine
simulator's stockpile (served by ``surrogate.rest.StorageView``) and the OPC
UA stockpile client (``surrogate.stockpile.StockpileAsset``) both call them,
so both show the same thing for the same particles.

Layout. A model with ``has_geometry`` (ROM, DEM) is shown at its particles'
own positions and velocities in the pile's x-y plane (x horizontal, y up,
[m]). A model without (FIFO, mixing) has no positions: ``schematic_layout``
draws its held particles in a half disc of radius ``radius`` [m] above the
outlet at the origin, by their rank in the order of leaving: an illustration
of what leaves first, not a flow simulation.

Origin. ``origin`` of a particle is the index of the source it was mined at,
the store's extrinsic attribute ``source`` (int64; -1: unknown, or a store
without that attribute). In the mine simulator it is the owner index of the
``Source`` asset that created the particle; in the OPC UA stockpile it is
the plant's source number of the inbound bin. ``origin_names`` names each
index held.

Units: SI (kg, m, s, kg/s); grade and hardness dimensionless.
"""

from __future__ import annotations

import numba
import numpy as np

from cosim.errors import ValidationError, check_finite_range
from cosim.sizes import d_passing

SOURCE_ATTRIBUTE = "source"
"""Extrinsic particle attribute holding the source index (``origin``)."""

MAX_GRID_CELLS = 1024
"""Largest side [cells] of ``fields``."""


def held_slots(storage) -> np.ndarray:
    """Store slots of the particles the storage holds."""
    return storage.particles.owned_by(storage.owner)


def layout(storage) -> str:
    """``particles`` (the model's own positions) or ``schematic`` (no geometry)."""
    return "particles" if type(storage).has_geometry else "schematic"


def schematic_layout(order, held_mass: float, discharge_rate: float, radius: float):
    """Display positions and velocities for a storage model without geometry.

    The particle whose rank in the order of leaving ``order`` is a fraction
    ``s`` of the held particles sits at radius ``R sqrt(s)`` from the outlet
    at the origin (area-uniform in the half disc of radius ``R`` [m]), at
    an angle in [0, pi] fixed by its id (golden-ratio hash), and moves
    radially at d(R sqrt(s))/dt with ds/dt = -discharge_rate / held_mass.
    Returns ``x, y`` [m] and ``vx, vy`` [m/s].
    """
    n = len(order)
    s = (np.arange(n) + 0.5) / max(n, 1)
    theta = np.pi * np.mod(np.asarray(order, dtype=np.float64) * 0.6180339887498949, 1.0)
    r = radius * np.sqrt(s)
    speed = -radius * (discharge_rate / max(held_mass, 1e-300)) / (2.0 * np.sqrt(s))
    cos, sin = np.cos(theta), np.sin(theta)
    return r * cos, r * sin, speed * cos, speed * sin


def display(storage, discharge_rate: float, radius: float):
    """``(slots, x, y, vx, vy)`` of the held particles in the display plane [m, m/s]."""
    store = storage.particles
    if type(storage).has_geometry:
        slots = held_slots(storage)
        return (slots, store.position[slots, 0], store.position[slots, 1],
                store.velocity[slots, 0], store.velocity[slots, 1])
    order = storage.held_ids()
    slots = store.slots(order)
    return (slots, *schematic_layout(order, float(store.mass[slots].sum()),
                                     discharge_rate, radius))


def _weighted_mean(weights: np.ndarray, values: np.ndarray) -> float:
    """Mean of ``values`` (N,) weighted by ``weights`` (N,); NaN when the weights
    sum to 0. Numpy's pairwise sums, not BLAS: the same result every run."""
    total = float(weights.sum())
    if not total > 0:
        return float("nan")
    return float((weights * values).sum() / total)


def _mean_size_distribution(weights: np.ndarray, f: np.ndarray, slots: np.ndarray):
    """The size distribution (16,) of the particles at ``slots`` of the store's
    fractions ``f`` (N, 16), weighted by ``weights`` (one per slot); NaN when the
    weights sum to 0."""
    total = float(weights.sum())
    if not total > 0:
        return np.full(f.shape[1], np.nan)
    return _weighted_row_sum(np.ascontiguousarray(weights, dtype=np.float64), f,
                             np.ascontiguousarray(slots, dtype=np.int64)) / total


@numba.njit(cache=True)
def _weighted_row_sum(weights, values, rows):
    # rows added one after another, as numpy sums an (N, k) array over axis 0 (the
    # same result to the bit), without its (N, k) temporaries: 3.5 ms a call on a
    # 19,000-particle pile, every step, against 0.13 ms
    out = np.zeros(values.shape[1])
    for k in range(rows.size):
        row = rows[k]
        for j in range(values.shape[1]):
            out[j] += weights[k] * values[row, j]
    return out


def totals(storage, *, time: float, discharge_rate: float,
           discharge_actual: float) -> dict:
    """Held mass [kg], mass-weighted grade and hardness (the paper's eq. observation
    over the particles held), D80 [m], count, discharge setpoint and actual rate
    [kg/s] and time [s]; NaN averages when empty."""
    store = storage.particles
    slots = held_slots(storage)
    mass = store.mass[slots]
    f = _mean_size_distribution(mass, store.f, slots)
    return {"time_s": float(time), "held_mass_kg": float(mass.sum()),
            "grade": _weighted_mean(mass, store.grade[slots]),
            "hardness": _weighted_mean(mass, store.hardness[slots]),
            "d80_m": float("nan") if np.isnan(f).any() else float(d_passing(f, 0.8)),
            "particle_count": int(slots.size),
            "discharge_rate_kg_s": float(discharge_rate),
            "discharge_actual_kg_s": float(discharge_actual)}


def _edges(values: np.ndarray, cells: int) -> np.ndarray:
    """Cell edges spanning ``values``; 1 m wide span around a degenerate one."""
    if values.size == 0:
        low, high = 0.0, 1.0
    else:
        low, high = float(values.min()), float(values.max())
    if not high - low > 1e-9:
        low, high = low - 0.5, high + 0.5
    # widen a hair so the largest value falls inside the last cell
    return np.linspace(low, high + 1e-9 * max(1.0, abs(high)), cells + 1)


def fields(storage, nx: int, ny: int, *, time: float, discharge_rate: float,
           radius: float) -> dict:
    """Mass [kg] per cell and mass-weighted grade, hardness, residence time [s] and
    velocity ``vx``, ``vy`` [m/s] on an ``ny`` x ``nx`` grid (row 0 at the lowest y;
    averages NaN where a cell is empty). The grid spans the held particles of a
    model with geometry, the schematic half disc [-radius, radius] x [0, radius]
    otherwise."""
    for name, value in (("nx", nx), ("ny", ny)):
        if not 1 <= int(value) <= MAX_GRID_CELLS:
            raise ValidationError(name, f"an integer in [1, {MAX_GRID_CELLS}]",
                                  f"got {value!r}")
    slots, x, y, vx, vy = display(storage, discharge_rate, radius)
    store = storage.particles
    if type(storage).has_geometry:
        x_edges, y_edges = _edges(x, int(nx)), _edges(y, int(ny))
    else:
        x_edges = np.linspace(-radius, radius * (1 + 1e-9), int(nx) + 1)
        y_edges = np.linspace(0.0, radius * (1 + 1e-9), int(ny) + 1)
    mass = store.mass[slots]

    def binned(weights):
        return np.histogram2d(y, x, bins=(y_edges, x_edges), weights=weights)[0]

    cell_mass = binned(mass)
    out = {"x_edges": x_edges, "y_edges": y_edges, "mass": cell_mass}
    quantities = {"grade": store.grade[slots], "hardness": store.hardness[slots],
                  "residence_time": time - store.time_in_owner[slots], "vx": vx, "vy": vy}
    with np.errstate(invalid="ignore", divide="ignore"):
        for name, values in quantities.items():
            out[name] = np.where(cell_mass > 0, binned(mass * values) / cell_mass, np.nan)
    return out


def _tracking(store, slots) -> np.ndarray:
    """The ``tracking_id`` attribute of ``slots``, else their ids."""
    if "tracking_id" in store.attribute_names:
        return store.attribute("tracking_id")[slots]
    return store.id[slots]


def origins(store, slots) -> np.ndarray:
    """Source index (``origin``, see module docstring) of ``slots``; -1 where unknown."""
    if SOURCE_ATTRIBUTE in store.attribute_names:
        return store.attribute(SOURCE_ATTRIBUTE)[slots].astype(np.int64)
    return np.full(len(slots), -1, dtype=np.int64)


def particle_table(storage, limit: int, offset: int, *, time: float, discharge_rate: float,
                   radius: float) -> dict:
    """Rows ``offset .. offset + limit`` of the held particles ordered by id: id,
    tracking_id, x, y [m] (the layout's), mass [kg], grade, hardness,
    residence_time [s], origin (source index), and ``total`` (held count)."""
    for name, value in (("limit", limit), ("offset", offset)):
        if int(value) < 0:
            raise ValidationError(name, "an integer >= 0", f"got {value!r}")
    store = storage.particles
    slots, x, y, _, _ = display(storage, discharge_rate, radius)
    page = np.argsort(store.id[slots], kind="stable")[int(offset): int(offset) + int(limit)]
    rows = slots[page]
    return {"total": int(slots.size), "id": store.id[rows], "tracking_id": _tracking(store, rows),
            "x": x[page], "y": y[page], "mass": store.mass[rows], "grade": store.grade[rows],
            "hardness": store.hardness[rows], "residence_time": time - store.time_in_owner[rows],
            "origin": origins(store, rows)}


def origin_names(storage, names: dict | None = None) -> dict[int, str]:
    """Display name per origin (source index) held: ``names[index]``, else "source N"."""
    names = names or {}
    store = storage.particles
    held = np.unique(origins(store, held_slots(storage)))
    return {int(k): names.get(int(k), "unknown source" if k < 0 else f"source {int(k)}")
            for k in held}


def predicted_feed(storage, horizon_s: float, discharge_rate: float) -> dict:
    """The feed the storage model predicts for the next ``horizon_s`` [s] at
    ``discharge_rate`` [kg/s]: mass [kg], mass-weighted grade, hardness and
    D80 [m] (NaN when nothing is expected), particle count, the tracking
    ids expected and the mass [kg] per origin (``mass_by_origin``, source
    index -> kg, see ``origins``)."""
    return predicted_feeds(storage, (horizon_s,), discharge_rate)[0]


def predicted_feeds(storage, horizons_s, discharge_rate: float) -> list[dict]:
    """``predicted_feed`` for each of ``horizons_s`` [s], from one forecast of the
    model (``StorageModel.predict_each``)."""
    horizons_s = [float(check_finite_range("horizon_s", h, 0.0, unit="s")) for h in horizons_s]
    return [_feed_summary(storage.particles, horizon, ids, share) for horizon, (ids, share)
            in zip(horizons_s, storage.predict_each(horizons_s, discharge_rate))]


def _feed_summary(store, horizon_s: float, ids: np.ndarray, share: np.ndarray) -> dict:
    slots = store.slots(ids)
    mass = float(share.sum())
    grade = _weighted_mean(share, store.grade[slots])
    hardness = _weighted_mean(share, store.hardness[slots])
    d80 = float(d_passing(_mean_size_distribution(share, store.f, slots), 0.8)) \
        if mass > 0 else np.nan
    sources, which = np.unique(origins(store, slots), return_inverse=True)
    by_origin = np.bincount(which.ravel(), weights=share, minlength=sources.size)
    return {"horizon_s": horizon_s, "mass_kg": mass, "grade": grade, "hardness": hardness,
            "d80_m": d80, "particle_count": int(ids.size),
            "tracking_ids": np.unique(_tracking(store, slots)),
            "mass_by_origin": {int(k): float(m) for k, m in zip(sources, by_origin)}}
