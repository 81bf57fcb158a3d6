"""Structure-of-arrays store of pseudo-particles.

Source: paper section "Digital twin as a distributed particle simulation":
a pseudo-particle n has state X_n = [m_n, x_n, v_n, f_n, c_n, h_n], a position
of origin x_n(t0) (and its block i in the block model), and extrinsic
attributes written by observations along the chain (MWD signal, observed
crushability or grindability, ...); docs/architecture.md, "Data flow".

One store holds every particle of a scenario; the asset that currently holds
a particle is its ``owner`` (an integer the co-simulation assigns per asset,
``NO_OWNER`` for none). Moving a particle between assets changes one integer,
so no particle data is copied at an asset boundary.

Rows are kept dense: removing particles moves the last rows into the holes,
so removal costs O(removed) and a particle's row index ("slot") may change on
any removal. Hold particles by id; translate ids to slots with ``slots()``
right before use.

All fields are SI: mass [kg], position/velocity/origin [m, m/s], grade [-]
(mineral concentration, mass fraction in [0, 1]), hardness [-] (relative,
> 0; 1 is the paper's reference ore).
"""

from __future__ import annotations

from typing import Iterator

import numba
import numpy as np

from cosim.errors import ValidationError, check_finite_range
from cosim.sizes import N_CLASSES, check_fractions

NO_OWNER = -1
"""Owner value of a particle that no asset holds."""

MAX_ID = 2**32
"""Particle ids must be below this bound (ids index a dense lookup table)."""

# name -> (dtype, trailing shape)
CORE_FIELDS: dict[str, tuple[type, tuple[int, ...]]] = {
    "id": (np.uint64, ()),
    "mass": (np.float64, ()),
    "position": (np.float64, (3,)),
    "velocity": (np.float64, (3,)),
    "f": (np.float64, (N_CLASSES,)),
    "grade": (np.float64, ()),
    "hardness": (np.float64, ()),
    "origin": (np.float64, (3,)),
    "origin_block": (np.int64, ()),
    "owner": (np.int32, ()),
    "time_in_owner": (np.float64, ()),
}
"""Intrinsic fields every particle has. ``time_in_owner`` [s] is the time the
particle entered its current owner (residence time = now - time_in_owner)."""


def _broadcast(field: str, value, shape: tuple[int, ...], dtype) -> np.ndarray:
    """``value`` broadcast to ``shape``, or a ValidationError naming ``field``."""
    arr = np.asarray(value, dtype=dtype)
    try:
        return np.broadcast_to(arr, shape)
    except ValueError:
        raise ValidationError(field, f"a scalar or an array of shape {shape}",
                              f"got shape {arr.shape}") from None


@numba.njit(cache=True)
def _lookup_slots(slot_of_id, ids, slots) -> bool:
    """slots[i] = slot_of_id[ids[i]]; False at the first id outside the table or unmapped
    (``ParticleStore.slots`` then says which)."""
    size = np.uint64(slot_of_id.size)
    for i in range(ids.size):
        key = ids[i]
        if key >= size:
            return False
        slot = slot_of_id[key]
        if slot < 0:
            return False
        slots[i] = slot
    return True


class ParticleStore:
    """Structure-of-arrays store of pseudo-particles with stable uint64 ids.

    Parameters
    ----------
    capacity : int
        Initial number of rows; the store doubles it whenever it runs out.
    first_id : int
        First id handed out by ``add`` when ids are not given (default 0).

    Field arrays are exposed as views of the live rows: ``store.mass``,
    ``store.f`` (N, 16), ``store.position`` (N, 3), ... and
    ``store.attribute(name)`` for extrinsic attributes. Writing into a view
    writes the store.
    """

    def __init__(self, capacity: int = 1024, first_id: int = 0):
        self._capacity = max(int(capacity), 1)
        self._n = 0
        self._next_id = int(first_id)
        self._arrays: dict[str, np.ndarray] = {
            name: np.zeros((self._capacity,) + shape, dtype=dtype)
            for name, (dtype, shape) in CORE_FIELDS.items()
        }
        self._attributes: dict[str, tuple[np.dtype, object]] = {}
        self._slot_of_id = np.full(max(self._next_id, 1024), -1, dtype=np.int64)

    # ------------------------------------------------------------------ views
    def __len__(self) -> int:
        return self._n

    def _view(self, name: str) -> np.ndarray:
        return self._arrays[name][: self._n]

    id = property(lambda self: self._view("id"), doc="Particle ids (uint64).")
    mass = property(lambda self: self._view("mass"), doc="Mass [kg].")
    position = property(lambda self: self._view("position"), doc="Position [m] (N, 3).")
    velocity = property(lambda self: self._view("velocity"), doc="Velocity [m/s] (N, 3).")
    f = property(lambda self: self._view("f"), doc="Size-class mass fractions (N, 16).")
    grade = property(lambda self: self._view("grade"), doc="Grade [-] in [0, 1].")
    hardness = property(lambda self: self._view("hardness"), doc="Hardness [-] > 0.")
    origin = property(lambda self: self._view("origin"), doc="Position of origin [m] (N, 3).")
    origin_block = property(lambda self: self._view("origin_block"),
                            doc="Block-model cell of origin (-1 if none).")
    owner = property(lambda self: self._view("owner"), doc="Owner asset index (int32).")
    time_in_owner = property(lambda self: self._view("time_in_owner"),
                             doc="Time [s] the particle entered its current owner.")

    @property
    def attribute_names(self) -> list[str]:
        """Names of the extrinsic attributes added so far."""
        return list(self._attributes)

    @property
    def field_names(self) -> list[str]:
        """All field names: the intrinsic ones, then the extrinsic attributes."""
        return list(CORE_FIELDS) + list(self._attributes)

    def attribute(self, name: str) -> np.ndarray:
        """View of an extrinsic attribute (or of an intrinsic scalar field) by name."""
        if name in self._arrays:
            return self._view(name)
        raise ValidationError("attribute", f"one of {self.field_names}", f"got {name!r}")

    def add_attribute(self, name: str, dtype=np.float64, default=np.nan) -> None:
        """Add an extrinsic attribute (e.g. ``"mwd"``); existing rows get ``default``.

        Adding an attribute that exists with the same dtype is a no-op.
        """
        if name in CORE_FIELDS:
            raise ValidationError("name", f"not an intrinsic field {list(CORE_FIELDS)}",
                                  f"got {name!r}")
        if not name.isidentifier():
            raise ValidationError("name", "a Python identifier", f"got {name!r}")
        dtype = np.dtype(dtype)
        if name in self._attributes:
            if self._attributes[name][0] != dtype:
                raise ValidationError(name, f"dtype {self._attributes[name][0]}",
                                      f"attribute exists; got dtype {dtype}")
            return
        self._attributes[name] = (dtype, default)
        self._arrays[name] = np.full(self._capacity, default, dtype=dtype)

    # ------------------------------------------------------------- id lookup
    def slots(self, ids) -> np.ndarray:
        """Row indices of ``ids``; an unknown id is a ``ValidationError``."""
        ids = np.asarray(ids, dtype=np.uint64).ravel()
        slots = np.empty(ids.size, dtype=np.int64)
        # called many times a step: one compiled pass when every id is known
        if _lookup_slots(self._slot_of_id, ids, slots):
            return slots
        inside = ids < self._slot_of_id.size
        slots = np.full(ids.size, -1, dtype=np.int64)
        slots[inside] = self._slot_of_id[ids[inside].astype(np.int64)]
        bad = ids[slots < 0]
        raise ValidationError("id", "the id of a particle in the store",
                              f"unknown id {int(bad[0])}; {bad.size} unknown")

    def contains(self, ids) -> np.ndarray:
        """Boolean array: which of ``ids`` are in the store."""
        ids = np.asarray(ids, dtype=np.uint64).ravel()
        inside = ids < self._slot_of_id.size
        out = np.zeros(ids.size, dtype=bool)
        out[inside] = self._slot_of_id[ids[inside].astype(np.int64)] >= 0
        return out

    # ------------------------------------------------------------------- add
    def add(self, *, mass, f, grade, hardness, position=None, velocity=None,
            origin=None, origin_block=-1, owner=NO_OWNER, time=0.0, ids=None,
            **attributes) -> np.ndarray:
        """Add a batch of particles and return their ids (uint64).

        Every argument is broadcast to the batch size given by ``mass``.
        The batch is validated as a whole before anything is written, so a
        refused batch leaves the store unchanged.

        Parameters
        ----------
        mass : array_like
            Mass [kg], finite and > 0.
        f : array_like (16,) or (N, 16)
            Size-class fractions in [0, 1] summing to 1 (tolerance 1e-6;
            accepted rows are renormalised to sum exactly to 1).
        grade : array_like
            Mineral concentration [-] in [0, 1].
        hardness : array_like
            Relative hardness [-], finite and > 0.
        position, velocity, origin : array_like (3,) or (N, 3), optional
            [m], [m/s], [m]; default zero; ``origin`` defaults to ``position``.
        origin_block : int or array_like
            Block-model cell of origin, -1 for none.
        owner : int or array_like
            Owner asset index.
        time : float or array_like
            Time [s] each particle entered its owner, stored as
            ``time_in_owner`` (one per particle: a batch of bins that arrived
            at different times).
        ids : array_like, optional
            Explicit ids (e.g. particles arriving from another process);
            by default fresh ids are handed out.
        **attributes
            Values of extrinsic attributes (added with ``add_attribute``).
        """
        mass = check_finite_range("mass", np.atleast_1d(mass), 0.0, low_open=True, unit="kg")
        if mass.ndim != 1:
            raise ValidationError("mass", "a scalar or 1-D array", f"got shape {mass.shape}")
        count = mass.size
        values = {"mass": mass}
        f = check_fractions(_broadcast("f", f, (count, N_CLASSES), np.float64))
        values["f"] = f / f.sum(axis=1, keepdims=True)
        values["grade"] = check_finite_range(
            "grade", _broadcast("grade", grade, (count,), np.float64), 0.0, 1.0)
        values["hardness"] = check_finite_range(
            "hardness", _broadcast("hardness", hardness, (count,), np.float64),
            0.0, low_open=True)
        for name, given in (("position", position), ("velocity", velocity)):
            values[name] = self._vector(name, 0.0 if given is None else given, count)
        values["origin"] = (values["position"] if origin is None
                            else self._vector("origin", origin, count))
        values["origin_block"] = _broadcast("origin_block", origin_block, (count,), np.int64)
        values["owner"] = _broadcast("owner", owner, (count,), np.int32)
        values["time_in_owner"] = _broadcast("time", time, (count,), np.float64)
        for name, value in attributes.items():
            if name not in self._attributes:
                raise ValidationError("attributes", f"names among {self.attribute_names}",
                                      f"unknown attribute {name!r}; add it with add_attribute")
            values[name] = _broadcast(name, value, (count,), self._attributes[name][0])
        if ids is None:
            new_ids = np.arange(self._next_id, self._next_id + count, dtype=np.uint64)
        else:
            new_ids = np.asarray(ids, dtype=np.uint64).ravel()
            if new_ids.size != count:
                raise ValidationError("ids", f"{count} ids, one per particle",
                                      f"got {new_ids.size}")
            if np.unique(new_ids).size != count or self.contains(new_ids).any():
                raise ValidationError("ids", "ids not already in the store and not repeated")
        if count and int(new_ids.max()) >= MAX_ID:
            raise ValidationError("ids", f"< {MAX_ID}", f"got {int(new_ids.max())}")
        values["id"] = new_ids

        self._reserve(self._n + count)
        rows = slice(self._n, self._n + count)
        for name, value in values.items():
            self._arrays[name][rows] = value
        for name, (_, default) in self._attributes.items():
            if name not in values:
                self._arrays[name][rows] = default
        self._map_ids(new_ids, np.arange(self._n, self._n + count))
        self._n += count
        if count:
            self._next_id = max(self._next_id, int(new_ids.max()) + 1)
        return new_ids

    @staticmethod
    def _vector(name, value, count):
        return check_finite_range(name, _broadcast(name, value, (count, 3), np.float64), unit="m")

    def _reserve(self, needed: int) -> None:
        if needed <= self._capacity:
            return
        capacity = self._capacity
        while capacity < needed:
            capacity *= 2
        for name, arr in self._arrays.items():
            grown = np.empty((capacity,) + arr.shape[1:], dtype=arr.dtype)
            grown[: self._n] = arr[: self._n]
            self._arrays[name] = grown
        self._capacity = capacity

    def _map_ids(self, ids: np.ndarray, slots: np.ndarray) -> None:
        if ids.size == 0:
            return
        top = int(ids.max()) + 1
        if top > self._slot_of_id.size:
            grown = np.full(max(top, 2 * self._slot_of_id.size), -1, dtype=np.int64)
            grown[: self._slot_of_id.size] = self._slot_of_id
            self._slot_of_id = grown
        self._slot_of_id[ids.astype(np.int64)] = slots

    # ---------------------------------------------------------------- remove
    def remove(self, ids) -> int:
        """Remove the particles with ``ids``; unknown ids are refused (nothing removed)."""
        return self.remove_slots(self.slots(ids))

    def remove_slots(self, slots) -> int:
        """Remove the particles in rows ``slots``; O(len(slots)).

        The last live rows are moved into the holes, so slots of other
        particles may change.
        """
        slots = np.unique(np.asarray(slots, dtype=np.int64))
        if slots.size == 0:
            return 0
        if slots[0] < 0 or slots[-1] >= self._n:
            raise ValidationError("slots", f"row indices in [0, {self._n})")
        new_n = self._n - slots.size
        removed_ids = self._arrays["id"][slots].astype(np.int64)
        holes = slots[slots < new_n]
        staying = np.ones(slots.size, dtype=bool)  # the tail rows not removed move
        staying[slots[slots >= new_n] - new_n] = False
        movers = np.arange(new_n, self._n)[staying]
        for arr in self._arrays.values():
            arr[holes] = arr[movers]
        self._slot_of_id[removed_ids] = -1
        self._slot_of_id[self._arrays["id"][holes].astype(np.int64)] = holes
        self._n = new_n
        return int(slots.size)

    # ----------------------------------------------------------- selections
    def where(self, mask) -> np.ndarray:
        """Ids of the particles where the boolean ``mask`` (length N) is true."""
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (self._n,):
            raise ValidationError("mask", f"a boolean array of length {self._n}",
                                  f"got shape {mask.shape}")
        return self.id[mask].copy()

    def owned_by(self, owner: int) -> np.ndarray:
        """Slots of the particles held by asset ``owner``."""
        return np.flatnonzero(self.owner == owner)

    def by_owner(self) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(owner, slots)`` for every owner that holds particles."""
        owners = self.owner
        order = np.argsort(owners, kind="stable")
        values, starts = np.unique(owners[order], return_index=True)
        bounds = np.append(starts, order.size)
        for k, value in enumerate(values):
            yield int(value), order[bounds[k]: bounds[k + 1]]

    def set_owner(self, slots, owner: int, time: float) -> None:
        """Hand the particles in ``slots`` to asset ``owner`` at ``time`` [s]."""
        self._arrays["owner"][slots] = owner
        self._arrays["time_in_owner"][slots] = time

    def total_mass(self, owner: int | None = None) -> float:
        """Total mass [kg], of all particles or of one owner's."""
        if owner is None:
            return float(self.mass.sum())
        return float(self.mass[self.owner == owner].sum())

    def gather(self, slots=None, fields=None) -> dict[str, np.ndarray]:
        """Copies of the fields (default: all) for ``slots`` (default: all rows).

        The result is a plain dict of arrays (a "batch"): what an event
        records, and what ``add_batch`` takes to put particles into another
        store with the same ids.
        """
        names = self.field_names if fields is None else list(fields)
        for name in names:
            if name not in self._arrays:
                raise ValidationError("fields", f"names among {self.field_names}",
                                      f"got {name!r}")
        rows = slice(0, self._n) if slots is None else np.asarray(slots, dtype=np.int64)
        return {name: self._arrays[name][rows].copy() for name in names}

    def add_batch(self, batch: dict[str, np.ndarray], **overrides) -> np.ndarray:
        """Add particles from a ``gather`` batch, keeping their ids.

        Extrinsic attributes in the batch that this store lacks are added
        (float64 ones default to NaN, integer ones to 0).
        """
        batch = {**batch, **overrides}
        for name, values in batch.items():
            if name not in CORE_FIELDS and name not in self._attributes:
                values = np.asarray(values)
                self.add_attribute(name, values.dtype,
                                   np.nan if values.dtype.kind == "f" else 0)
        core = {k: batch[k] for k in ("mass", "f", "grade", "hardness", "position",
                                      "velocity", "origin", "origin_block", "owner")
                if k in batch}
        extra = {k: v for k, v in batch.items() if k not in CORE_FIELDS}
        ids = self.add(ids=batch.get("id"), time=0.0, **core, **extra)
        if "time_in_owner" in batch:
            self._arrays["time_in_owner"][self.slots(ids)] = batch["time_in_owner"]
        return ids

    def to_dataframe(self, slots=None):
        """The particles (default: all) as a pandas DataFrame, ``f`` as f0..f15."""
        import pandas as pd

        data = self.gather(slots)
        columns = {}
        for name, values in data.items():
            if values.ndim == 1:
                columns[name] = values
            else:
                labels = ("x", "y", "z") if values.shape[1] == 3 else range(values.shape[1])
                prefix = {"position": "", "velocity": "v", "origin": "origin_"}.get(name, name)
                for k, label in enumerate(labels):
                    columns[f"{prefix}{label}"] = values[:, k]
        return pd.DataFrame(columns)
