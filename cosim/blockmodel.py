"""Block model of an ore body, hardness profiles and the MWD signal.

Source: paper section "Digital twin as a distributed particle simulation"
(block model of grid cells i with centre x_i, volume V_i and a priori
properties), section "Simulator" (hardness function h(x) at the left source:
constant 1, or a step 1 -> 2) and section "Identification of hardness from
measurement-while-drilling" (quadratic profile between 1 and 2; MWD signal
s_n = h(x_n + R(-dx, dx))**beta with a uniform location error).

Hardness profiles are functions of the coordinate along the mining
direction (axis 0 of the ore body, metres from the block model's origin),
because the loading point advances along it as material is taken.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cosim.errors import ValidationError, check_finite_range
from cosim.numerics import power


@dataclass(frozen=True)
class ConstantHardness:
    """h(x) = value [-] everywhere (paper: the right source, h = 1)."""

    value: float = 1.0

    def __call__(self, x) -> np.ndarray:
        return np.full(np.shape(x), self.value, dtype=np.float64)


@dataclass(frozen=True)
class StepHardness:
    """h(x) = before for x < at, else after (paper "Step response": 1 -> 2).

    at [m] along the mining direction; before, after [-].
    """

    at: float
    before: float = 1.0
    after: float = 2.0

    def __call__(self, x) -> np.ndarray:
        return np.where(np.asarray(x, dtype=np.float64) < self.at, self.before, self.after)


@dataclass(frozen=True)
class QuadraticHardness:
    """Quadratic profile between ``low`` and ``high`` over [start, end] [m].

    h(u) = low + (high - low) * (1 - (2u - 1)**2), u = (x - start)/(end - start)
    clipped to [0, 1]: ``low`` at both ends, ``high`` mid-way (paper figure
    "hardness_vs_MWD_tracking_error": a continuous profile between 1 and 2).
    """

    start: float = 0.0
    end: float = 100.0
    low: float = 1.0
    high: float = 2.0

    def __call__(self, x) -> np.ndarray:
        u = np.clip((np.asarray(x, dtype=np.float64) - self.start) / (self.end - self.start),
                    0.0, 1.0)
        return self.low + (self.high - self.low) * (1.0 - (2.0 * u - 1.0) ** 2)


def hardness_function(spec: dict):
    """Build a hardness profile from a config table, e.g. ``{"kind": "step", "at": 20}``."""
    kinds = {"constant": ConstantHardness, "step": StepHardness, "quadratic": QuadraticHardness}
    spec = dict(spec)
    kind = spec.pop("kind", None)
    if kind not in kinds:
        raise ValidationError("hardness.kind", f"one of {sorted(kinds)}", f"got {kind!r}")
    try:
        return kinds[kind](**spec)
    except TypeError as exc:
        raise ValidationError(f"hardness ({kind})", "the documented parameters",
                              str(exc)) from None


def mwd_signal(hardness, x, *, beta: float = 0.4, location_error: float = 0.0,
               rng: np.random.Generator | None = None) -> np.ndarray:
    """Measurement-while-drilling signal s = h(x + R(-dx, dx))**beta.

    Parameters
    ----------
    hardness : callable
        Hardness profile h(x).
    x : array_like
        Positions [m] along the mining direction where the signal is recorded.
    beta : float
        Exponent of the true relation s = h**beta (paper: 0.4).
    location_error : float
        Half-width dx [m] of the uniform location error (paper: 12.5 m).
    rng : numpy.random.Generator
        Needed when ``location_error > 0``.
    """
    x = np.asarray(x, dtype=np.float64)
    if location_error > 0:
        if rng is None:
            raise ValidationError("rng", "a numpy Generator when location_error > 0")
        x = x + rng.uniform(-location_error, location_error, size=x.shape)
    return power(hardness(x), beta)


@dataclass
class BlockModel:
    """Regular grid of ore-body cells with a priori properties.

    Parameters
    ----------
    origin : (3,) array_like
        Corner of the grid [m].
    cell_size : (3,) array_like
        Cell edge lengths [m] (2D scenes use one cell across y and z).
    shape : (3,) tuple of int
        Number of cells along each axis.
    density : float
        In-situ density [kg/m^3] used for block masses, default 2700.
    properties : dict
        Per-cell a priori properties (``hardness``, ``grade``,
        ``grindability``, ``grindability_confidence``, ...), arrays of
        length ``n_cells``.
    """

    origin: np.ndarray
    cell_size: np.ndarray
    shape: tuple[int, int, int]
    density: float = 2700.0
    properties: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        self.origin = check_finite_range("origin", np.asarray(self.origin, float).reshape(3),
                                         unit="m")
        self.cell_size = check_finite_range(
            "cell_size", np.asarray(self.cell_size, float).reshape(3), 0.0, low_open=True,
            unit="m")
        self.shape = tuple(int(s) for s in self.shape)
        if len(self.shape) != 3 or min(self.shape) < 1:
            raise ValidationError("shape", "three positive cell counts", f"got {self.shape}")
        check_finite_range("density", self.density, 0.0, low_open=True, unit="kg/m^3")
        for name, values in self.properties.items():
            self.properties[name] = self._per_cell(name, values)

    @classmethod
    def along(cls, start: float, length: float, block_length: float, *, width: float = 20.0,
              height: float = 10.0, hardness=ConstantHardness(), grade: float = 0.5,
              density: float = 2700.0, grindability_confidence: float = 0.1) -> "BlockModel":
        """A row of blocks along the mining direction (the 2D simulator's ore body).

        Hardness per block is the profile at the block centre; the a priori
        grindability is 1/hardness (harder ore grinds worse), with confidence
        ``grindability_confidence`` (the paper's alpha_i^0, default 0.1).
        """
        n = max(int(round(length / block_length)), 1)
        model = cls(origin=(start, 0.0, 0.0), cell_size=(length / n, width, height),
                    shape=(n, 1, 1), density=density)
        h = hardness(model.centres[:, 0])
        model.properties.update(
            hardness=h, grade=np.full(n, grade, dtype=float), grindability=1.0 / h,
            grindability_confidence=np.full(n, grindability_confidence, dtype=float))
        return model

    @property
    def n_cells(self) -> int:
        return int(np.prod(self.shape))

    @property
    def centres(self) -> np.ndarray:
        """Cell centres [m] (n_cells, 3), x-fastest ordering."""
        idx = np.indices(self.shape[::-1]).reshape(3, -1).T[:, ::-1]
        return self.origin + (idx + 0.5) * self.cell_size

    @property
    def volumes(self) -> np.ndarray:
        """Cell volumes V_i [m^3]."""
        return np.full(self.n_cells, float(np.prod(self.cell_size)))

    @property
    def masses(self) -> np.ndarray:
        """Block masses m_i^0 [kg] = density * V_i."""
        return self.density * self.volumes

    def cell_of(self, positions) -> np.ndarray:
        """Cell index of each position (N, 3) [m]; -1 outside the grid."""
        pos = np.atleast_2d(np.asarray(positions, dtype=np.float64))
        ijk = np.floor((pos - self.origin) / self.cell_size).astype(np.int64)
        shape = np.asarray(self.shape)
        inside = np.all((ijk >= 0) & (ijk < shape), axis=1)
        flat = ijk[:, 0] + shape[0] * (ijk[:, 1] + shape[1] * ijk[:, 2])
        return np.where(inside, flat, -1)

    def _per_cell(self, name, values) -> np.ndarray:
        arr = np.broadcast_to(np.asarray(values, dtype=np.float64), (self.n_cells,)).copy()
        return check_finite_range(f"properties.{name}", arr)
