"""Virtual sensors: mass-weighted observations over particles in a volume.

Source: paper eq. (observation), section "Digital twin as a distributed
particle simulation":

    p(x, t) = < sum_{n in N(x,t)} m_n p_n / sum_{n in N(x,t)} m_n >_{t_w}

the mass-weighted attribute over the particles N(x, t) in a volume V(x, t),
with a moving average of window t_w to filter the effect of coarse
particles. For the size distribution the same average gives f(x, t), and
from it D80 and the mean diameter d.f.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numba
import numpy as np

from cosim.errors import ValidationError
from cosim.numerics import weighted_column_sums
from cosim.sizes import d_passing


@numba.njit(cache=True)
def _box_sums(position, mass, values, lo, hi):
    """Sum of m and m*p over particles inside the box [lo, hi) (values (N, K))."""
    n, k = values.shape
    total = 0.0
    weighted = np.zeros(k)
    for i in range(n):
        if (lo[0] <= position[i, 0] < hi[0] and lo[1] <= position[i, 1] < hi[1]
                and lo[2] <= position[i, 2] < hi[2]):
            m = mass[i]
            total += m
            for j in range(k):
                weighted[j] += m * values[i, j]
    return total, weighted


@dataclass(frozen=True)
class Box:
    """Axis-aligned box volume [lo, hi) in metres."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def contains(self, position: np.ndarray) -> np.ndarray:
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        return np.all((position >= lo) & (position < hi), axis=1)


def _as_columns(values: np.ndarray) -> np.ndarray:
    # explicit column count: reshape(-1) is ambiguous for an empty store
    columns = int(np.prod(values.shape[1:]))
    return values.reshape(values.shape[0], columns).astype(np.float64, copy=False)


def observe(store, attribute: str, *, box: Box | None = None, owner: int | None = None,
            slots=None):
    """Instantaneous mass-weighted mean of ``attribute`` (paper eq. observation).

    The volume is a ``box``, the particles of one ``owner`` asset, explicit
    ``slots``, or (none given) every particle. Returns a float, or an array
    for vector attributes such as ``"f"``; NaN where the volume holds no mass.
    """
    values = store.f if attribute == "f" else store.attribute(attribute)
    columns = _as_columns(np.asarray(values))
    mass = store.mass
    if box is not None:
        total, weighted = _box_sums(np.ascontiguousarray(store.position), mass,
                                    np.ascontiguousarray(columns),
                                    np.asarray(box.lo, float), np.asarray(box.hi, float))
    else:
        if owner is not None:
            slots = store.owned_by(owner)
        if slots is not None:
            mass, columns = mass[slots], columns[slots]
        total = float(mass.sum())
        weighted = weighted_column_sums(mass, columns)
    mean = weighted / total if total > 0 else np.full(columns.shape[1], np.nan)
    return float(mean[0]) if np.ndim(values) == 1 else mean


class VirtualSensor:
    """A virtual measurement of one attribute with a moving average of window t_w.

    Parameters
    ----------
    attribute : str
        ``"grade"``, ``"hardness"``, any extrinsic attribute, or ``"f"``
        (the size distribution; then ``d80`` is also reported).
    box, owner : optional
        The sensed volume: a ``Box``, or every particle of an owner asset.
    window : float
        Moving-average window t_w [s], default 30 (the paper's figures).

    ``sample(store, t)`` observes, stores the sample and returns the moving
    average over the samples of the last ``window`` seconds (samples with an
    empty volume are left out of the average).
    """

    def __init__(self, attribute: str, *, box: Box | None = None, owner: int | None = None,
                 window: float = 30.0):
        if not window >= 0:
            raise ValidationError("window", ">= 0 s", f"got {window!r}")
        self.attribute = attribute
        self.box = box
        self.owner = owner
        self.window = float(window)
        self._samples: deque = deque()
        self.value = np.nan
        self.average = np.nan

    def sample(self, store, t: float):
        value = observe(store, self.attribute, box=self.box, owner=self.owner)
        self.value = value
        if not np.all(np.isnan(value)):
            self._samples.append((t, value))
        while self._samples and self._samples[0][0] <= t - self.window:
            self._samples.popleft()
        if self._samples:
            self.average = np.mean([v for _, v in self._samples], axis=0)
        else:
            self.average = np.nan if np.ndim(value) == 0 else np.full(np.shape(value), np.nan)
        return self.average

    @property
    def d80(self) -> float:
        """D80 [m] of the averaged size distribution (attribute ``"f"`` only)."""
        if self.attribute != "f":
            raise ValidationError("attribute", "'f' for d80", f"sensor reads {self.attribute!r}")
        if np.any(np.isnan(self.average)):
            return float("nan")
        return float(d_passing(self.average, 0.8))
