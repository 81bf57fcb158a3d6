"""Floating-point reproducibility: the same seeded run, bit for bit, on every x86-64 CPU.

Two things make a numpy/numba program round differently on another processor:

- **BLAS.** ``a @ b`` and ``np.dot`` call OpenBLAS, which picks a kernel for the
  CPU it runs on (Haswell, Zen, SkylakeX, ...); the kernels sum in different
  orders and some fuse multiply-adds. Measured here: a seeded 900 s mixing run
  of ``examples/step_response.toml`` changed its events and time series under
  ``OPENBLAS_CORETYPE=Prescott``. The core's per-step reductions therefore go
  through the two kernels below, which sum in index order.
- **numba's target.** numba compiles for the host CPU (``NUMBA_CPU_NAME``);
  with ``fastmath`` LLVM may reassociate sums and contract ``a * b + c`` into
  an FMA, which depends on the instruction set. The core's kernels do not use
  ``fastmath``, so a FIFO or mixing mine run is bitwise the same on every
  x86-64 machine (``tests/test_reproducibility.py`` hashes one).

- **numpy's SIMD maths.** numpy picks its ``exp``, ``log``, ``power`` (and
  ``log10``, ``expm1``, ``log1p``, ``exp2``, ``cbrt``, ``arctan2``) loops by the
  CPU's instruction set at import; its AVX-512 loops (``X86_V4``) round the last
  bit differently from the AVX2 and baseline ones. Measured on an AMD EPYC with
  AVX-512: the seeded FIFO and mixing runs changed their digests, and the same
  machine with ``NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL"`` gave the digests
  recorded on a machine without AVX-512. The core's elementwise transcendental
  functions therefore go through ``exp``, ``log``, ``power`` and ``cbrt`` below, compiled
  loops over the C library's scalar functions, the same on every x86-64 CPU.

The DEM and the ROM's surface DEM are chaotic: a last-bit difference grows
until the trajectory is another one. Their hot kernels use ``fastmath`` for
speed (``HOT_JIT``) and so depend on the CPU. ``MINETWIN_REPRODUCIBLE=1``
turns ``fastmath`` off and compiles for numba's ``generic`` CPU, which makes
them the same on every x86-64 machine too, at a measured speed cost (README,
"Reproducibility across machines").
"""

from __future__ import annotations

import os

import numpy as np

REPRODUCIBLE = os.environ.get("MINETWIN_REPRODUCIBLE", "") == "1"
"""``MINETWIN_REPRODUCIBLE=1``: chaotic kernels compiled without fastmath for a generic CPU."""

if REPRODUCIBLE:
    from pathlib import Path

    import numba.core.config

    os.environ["NUMBA_CPU_NAME"] = "generic"
    # numba's cache keys hold the CPU target but not fastmath: code cached by a
    # generic-CPU run with fastmath would be loaded here, so this mode caches apart
    os.environ.setdefault("NUMBA_CACHE_DIR",
                          str(Path.home() / ".cache" / "minetwin" / "numba-reproducible"))
    # numba reads its environment when it is imported; re-read it before anything compiles
    numba.core.config.reload_config()

import math  # noqa: E402

from numba import njit  # noqa: E402

HOT_JIT = {"cache": True, "fastmath": not REPRODUCIBLE, "error_model": "numpy"}
"""numba options of the chaotic hot kernels (DEM, surface DEM): fastmath lets LLVM
reorder float arithmetic, which is still deterministic on one machine (restarts stay
bit for bit) but not across instruction sets; off with ``MINETWIN_REPRODUCIBLE=1``.
error_model="numpy" drops the zero-division checks."""


ANOTHER_CPU_ENV = {"OPENBLAS_CORETYPE": "Prescott", "NUMBA_CPU_NAME": "generic",
                   "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX2_Usable,-FMA_Usable,-AVX_Usable",
                   "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"}
"""Environment under which this machine computes as another x86-64 CPU would: OpenBLAS's
baseline kernel, numba compiling for a generic CPU, glibc's maths without AVX2 and FMA,
numpy's loops without AVX-512 (features the machine lacks are ignored). The nearest
stand-in for a second machine in a test."""


@njit(cache=True)
def _weighted_column_sums(weights, rows, out):
    for j in range(rows.shape[1]):
        out[j] = 0.0
    for i in range(rows.shape[0]):
        w = weights[i]
        for j in range(rows.shape[1]):
            out[j] += w * rows[i, j]


def weighted_column_sums(weights, rows) -> np.ndarray:
    """``weights @ rows`` summed in row order (no BLAS): shape (n,) x (n, k) -> (k,)."""
    rows = np.ascontiguousarray(rows, dtype=np.float64)
    weights = np.ascontiguousarray(weights, dtype=np.float64)
    if rows.ndim != 2 or weights.shape != rows.shape[:1]:
        raise ValueError(f"weights {weights.shape} and rows {rows.shape} do not match")
    out = np.empty(rows.shape[1])
    _weighted_column_sums(weights, rows, out)
    return out


@njit(cache=True)
def _rows_times_transpose(rows, matrix, out):
    for i in range(rows.shape[0]):
        for k in range(matrix.shape[0]):
            total = 0.0
            for j in range(rows.shape[1]):
                total += rows[i, j] * matrix[k, j]
            out[i, k] = total


def rows_times_transpose(rows, matrix) -> np.ndarray:
    """``rows @ matrix.T`` summed in index order (no BLAS): (n, k) x (m, k) -> (n, m)."""
    rows = np.asarray(rows, dtype=np.float64)
    single = rows.ndim == 1
    rows = np.ascontiguousarray(np.atleast_2d(rows))
    matrix = np.ascontiguousarray(matrix, dtype=np.float64)
    if matrix.ndim != 2 or rows.shape[1] != matrix.shape[1]:
        raise ValueError(f"rows {rows.shape} and matrix {matrix.shape} do not match")
    out = np.empty((rows.shape[0], matrix.shape[0]))
    _rows_times_transpose(rows, matrix, out)
    return out[0] if single else out


# Elementwise exp, log, power and cbrt that round the same on every x86-64 CPU: compiled
# loops over the C library's scalar functions (no fastmath, so nothing is reassociated),
# not numpy's loops chosen by the instruction set (module docstring). njit, not
# vectorize: compiled (or loaded from numba's cache) at the first call, not at import.
@njit(cache=True)
def _exp(x, out):
    for i in range(x.size):
        out[i] = math.exp(x[i])


@njit(cache=True)
def _log(x, out):
    for i in range(x.size):
        v = x[i]
        out[i] = math.log(v) if v > 0.0 else (-math.inf if v == 0.0 else math.nan)


@njit(cache=True)
def _power(base, exponent, out):
    for i in range(base.size):
        b, e = base[i], exponent[i]
        if b < 0.0 and e != math.floor(e):
            out[i] = math.nan
        elif b == 0.0 and e < 0.0:
            out[i] = math.inf
        else:
            out[i] = math.pow(b, e)


@njit(cache=True)
def _cbrt(x, out):
    for i in range(x.size):
        out[i] = np.cbrt(x[i])  # numba lowers this to the C library's cbrt


def _elementwise(kernel, *arrays):
    arrays = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in arrays))
    flat = [np.ascontiguousarray(a).ravel() for a in arrays]
    out = np.empty(flat[0].size)
    kernel(*flat, out)
    out = out.reshape(arrays[0].shape)
    return out if out.ndim else float(out)


def exp(x):
    """e**x, elementwise (numpy.exp's meaning; the same bits on every CPU)."""
    return _elementwise(_exp, x)


def log(x):
    """Natural logarithm, elementwise (numpy.log's meaning: -inf at 0, nan below;
    the same bits on every CPU)."""
    return _elementwise(_log, x)


def power(base, exponent):
    """base**exponent, elementwise and broadcast (numpy.power's meaning for floats; the
    same bits on every CPU)."""
    return _elementwise(_power, base, exponent)


def cbrt(x):
    """Cube root, elementwise (numpy.cbrt's meaning; the same bits on every CPU)."""
    return _elementwise(_cbrt, x)
