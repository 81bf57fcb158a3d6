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

from numba import njit  # noqa: E402

HOT_JIT = {"cache": True, "fastmath": not REPRODUCIBLE, "error_model": "numpy"}
"""numba options of the chaotic hot kernels (DEM, surface DEM): fastmath lets LLVM
reorder float arithmetic, which is still deterministic on one machine (restarts stay
bit for bit) but not across instruction sets; off with ``MINETWIN_REPRODUCIBLE=1``.
error_model="numpy" drops the zero-division checks."""


ANOTHER_CPU_ENV = {"OPENBLAS_CORETYPE": "Prescott", "NUMBA_CPU_NAME": "generic",
                   "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX2_Usable,-FMA_Usable,-AVX_Usable"}
"""Environment under which this machine computes as another x86-64 CPU would: OpenBLAS's
baseline kernel, numba compiling for a generic CPU, glibc's maths without AVX2 and FMA.
The nearest stand-in for a second machine in a test."""


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
