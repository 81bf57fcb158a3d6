"""Size classes: the 16 logarithmic classes, cumulative distributions, D_F.

Source: paper section "Digital twin as a distributed particle simulation"
(size distribution f_n in N_d classes, cumulative F^k, D_F by interpolation,
mean diameter d.f); the class diameters are ours (docs/architecture.md, "Units and
conventions").

Class k (0-based, k = 0..15) holds the mass fraction f^k of material with
size in (d_{k-1}, d_k], with d_k = 1e-5 m * r**k and r = 10**(1/3), so that
d_6 = 1 mm (the paper's 1-based N_gr-a = 7) and d_15 = 1 m. The lower edge of
class 0 is taken as d_{-1} = d_0 / r.

Two cumulative conventions appear in the field and both are offered:

* ``retained(f)``: the paper's F^k = sum_{k' >= k} f^{k'}, the mass fraction
  in class k or coarser.
* ``passing(f)``: P^k = sum_{k' <= k} f^{k'}, the mass fraction finer than
  d_k. ``d_passing(f, 0.8)`` is the D80 of mineral processing (80 % of the
  mass passes), which is what the Bond formula needs.
"""

from __future__ import annotations

import math

import numpy as np

from cosim.errors import ValidationError
from cosim.numerics import exp, log, power, rows_times_transpose

N_CLASSES = 16
"""Number of size classes N_d."""

RATIO = 10.0 ** (1.0 / 3.0)
"""Ratio r between neighbouring class diameters."""

# the C library's pow and log (as cosim.numerics'), without compiling anything at import
DIAMETERS = 1e-5 * np.array([RATIO ** float(k) for k in range(N_CLASSES)])
"""Class diameters d_k [m] (upper edge of class k)."""

_LOG_EDGES = np.array([math.log(d) for d in (DIAMETERS[0] / RATIO, *DIAMETERS)])


def class_of(diameter: float) -> int:
    """Index of the class whose interval (d_{k-1}, d_k] contains ``diameter`` [m]."""
    if not np.isfinite(diameter) or diameter <= 0:
        raise ValidationError("diameter", "finite and > 0 m", f"got {diameter!r}")
    k = int(np.searchsorted(DIAMETERS, diameter * (1 - 1e-12)))
    return min(k, N_CLASSES - 1)


def check_fractions(f, field: str = "f", atol: float = 1e-6) -> np.ndarray:
    """Return ``f`` as float64 (..., 16), refusing anything that is not a distribution.

    Each row must have 16 entries in [0, 1] summing to 1 within ``atol``.
    """
    arr = np.asarray(f, dtype=np.float64)
    if arr.shape[-1:] != (N_CLASSES,):
        raise ValidationError(field, f"an array with last dimension {N_CLASSES}",
                              f"got shape {arr.shape}")
    bad = ~np.isfinite(arr) | (arr < 0.0) | (arr > 1.0)
    if bad.any():
        first = np.argwhere(bad)[0]
        raise ValidationError(field, "fractions in [0, 1] summing to 1",
                              f"got {arr[tuple(first)]!r} at index {tuple(int(i) for i in first)}")
    sums = arr.sum(axis=-1)
    off = np.abs(sums - 1.0) > atol
    if np.any(off):
        first = np.argwhere(np.atleast_1d(off))[0]
        raise ValidationError(field, f"fractions in [0, 1] summing to 1 (tolerance {atol:g})",
                              f"row {tuple(int(i) for i in first)} sums to "
                              f"{np.atleast_1d(sums)[tuple(first)]!r}")
    return arr


def normalize(f) -> np.ndarray:
    """Clip to [0, inf) and rescale every row to sum exactly to 1 (float64)."""
    arr = np.clip(np.asarray(f, dtype=np.float64), 0.0, None)
    return arr / arr.sum(axis=-1, keepdims=True)


def retained(f) -> np.ndarray:
    """The paper's cumulative distribution F^k = sum_{k' >= k} f^{k'}."""
    arr = np.asarray(f, dtype=np.float64)
    return np.cumsum(arr[..., ::-1], axis=-1)[..., ::-1]


def passing(f) -> np.ndarray:
    """Mass fraction finer than d_k: P^k = sum_{k' <= k} f^{k'}."""
    return np.cumsum(np.asarray(f, dtype=np.float64), axis=-1)


def d_passing(f, fraction: float) -> np.ndarray:
    """Size D_F [m] below which ``fraction`` of the mass lies (D80 for 0.8).

    Linear interpolation of the passing curve in log(d) between class edges,
    so D_F is continuous and monotone non-decreasing in ``fraction``.
    Works on one distribution (16,) or many (N, 16).
    """
    if not (0.0 < fraction <= 1.0):
        raise ValidationError("fraction", "in (0, 1]", f"got {fraction!r}")
    arr = np.asarray(f, dtype=np.float64)
    single = arr.ndim == 1
    rows = np.atleast_2d(arr)
    cum = np.zeros((rows.shape[0], N_CLASSES + 1))
    cum[:, 1:] = np.cumsum(rows, axis=1)
    target = fraction * cum[:, -1]
    # first edge index j >= 1 whose passing fraction reaches the target
    j = np.clip((cum < target[:, None]).sum(axis=1), 1, N_CLASSES)
    idx = np.arange(rows.shape[0])
    p_lo, p_hi = cum[idx, j - 1], cum[idx, j]
    width = np.where(p_hi > p_lo, p_hi - p_lo, 1.0)
    w = np.clip((target - p_lo) / width, 0.0, 1.0)
    log_d = _LOG_EDGES[j - 1] + w * (_LOG_EDGES[j] - _LOG_EDGES[j - 1])
    out = exp(log_d)
    return out[0] if single else out


def mean_diameter(f) -> np.ndarray:
    """Mean particle diameter <d> = d . f [m] (paper, same section)."""
    return rows_times_transpose(f, DIAMETERS[None, :])[..., 0]


def fractions_from_cdf(cdf_at_upper_edges) -> np.ndarray:
    """Class fractions from a passing curve evaluated at d_0..d_15.

    Everything coarser than d_14 is put in the top class, so the result is a
    distribution even for a curve that has not reached 1 at d_15.
    """
    p = np.clip(np.asarray(cdf_at_upper_edges, dtype=np.float64), 0.0, 1.0)
    p = np.maximum.accumulate(p, axis=-1)
    f = np.diff(p, axis=-1, prepend=0.0)
    f[..., -1] = 1.0 - p[..., -2]
    return normalize(f)


def swebrec(x50: float = 0.1, x_max: float = 1.0, b: float = 2.0) -> np.ndarray:
    """Blast fragmentation by the Swebrec function, as 16 class fractions.

    P(x) = 1 / (1 + (ln(x_max/x) / ln(x_max/x50))**b) for x < x_max, else 1
    (Ouchterlony, "The Swebrec function", Mining Technology 114, 2005; review
    in Ouchterlony & Sanchidrian 2019, the paper's blasting reference).

    Parameters
    ----------
    x50 : float
        Median fragment size [m], default 0.1.
    x_max : float
        Largest fragment size [m], default 1.0 (in-situ block size).
    b : float
        Curve-undulation exponent [-], default 2.0.

    The defaults give the paper's figure "size_distribution": fragments from
    millimetres to a metre, about a quarter of the mass above the 0.25 m jaw
    gap.
    """
    if not (0 < x50 < x_max):
        raise ValidationError("x50", f"in (0, x_max={x_max:g}) m", f"got {x50!r}")
    if not b > 0:
        raise ValidationError("b", "> 0", f"got {b!r}")
    return fractions_from_cdf(_swebrec_cdf(np.array([x50]), x_max, b))[0]


def _swebrec_cdf(medians: np.ndarray, x_max: float, b: float) -> np.ndarray:
    """Swebrec passing fraction at the class edges for each median (N, 16)."""
    x = np.minimum(DIAMETERS, x_max)[None, :]
    with np.errstate(divide="ignore"):
        ratio = log(x_max / x) / log(x_max / medians[:, None])
    return np.where(x >= x_max, 1.0, 1.0 / (1.0 + power(ratio, b)))


def rosin_rammler(x_c: float = 0.15, n: float = 1.0) -> np.ndarray:
    """Blast fragmentation by Rosin-Rammler, as 16 class fractions.

    P(x) = 1 - exp(-(x / x_c)**n) (Rosin & Rammler 1933; the Kuz-Ram model of
    Cunningham 1983 uses this form).

    Parameters
    ----------
    x_c : float
        Characteristic size [m] (63.2 % passing), default 0.15.
    n : float
        Uniformity index [-], default 1.0.
    """
    if not x_c > 0:
        raise ValidationError("x_c", "> 0 m", f"got {x_c!r}")
    if not n > 0:
        raise ValidationError("n", "> 0", f"got {n!r}")
    return fractions_from_cdf(1.0 - exp(-power(DIAMETERS / x_c, n)))


def blasted_fractions(rng: np.random.Generator, count: int, *, x50: float = 0.1,
                      x_max: float = 1.0, b: float = 2.0,
                      x50_spread: float = 0.15) -> np.ndarray:
    """Per-particle after-blast distributions (count, 16).

    Each pseudo-particle gets a Swebrec distribution whose median is drawn
    log-normally around ``x50`` with relative spread ``x50_spread`` [-],
    because a real muck pile is not uniformly fragmented.
    """
    medians = np.clip(x50 * exp(x50_spread * rng.standard_normal(count)),
                      1e-4, 0.9 * x_max)
    return fractions_from_cdf(_swebrec_cdf(medians, x_max, b))
