"""Advection of bulk particles by a predicted velocity field (numba kernels).

Source: paper section "Digital twin as a distributed particle simulation":
"the computationally intense process of computing all contact forces is
substituted by a simple evaluation of the predicted velocity field at the
positions of the particles, which are simply advected using this velocity"
(Wallin and Servin 2021).

Equations: dx_n/dt = v(x_n), with v bilinearly interpolated between cell
centres of the predicted field (``(ny, nx, 2)`` [m/s]; outside the centres
the nearest edge value is used), integrated with the explicit midpoint rule
(second order) over ``substeps`` equal substeps of ``dt`` [s]. Positions are
then kept inside the container: x in [x_lo, x_hi], y >= y_lo [m] (walls and
floor, already shrunk by the particle radius by the caller).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, inline="always")
def sample(field, x0, y0, dx, dy, x, y):
    ny, nx = field.shape[0], field.shape[1]
    fx = (x - x0) / dx - 0.5
    fy = (y - y0) / dy - 0.5
    fx = min(max(fx, 0.0), nx - 1.0)
    fy = min(max(fy, 0.0), ny - 1.0)
    i = min(int(fx), nx - 2) if nx > 1 else 0
    j = min(int(fy), ny - 2) if ny > 1 else 0
    tx = fx - i if nx > 1 else 0.0
    ty = fy - j if ny > 1 else 0.0
    i1 = i + 1 if nx > 1 else i
    j1 = j + 1 if ny > 1 else j
    u = ((1 - tx) * (1 - ty) * field[j, i, 0] + tx * (1 - ty) * field[j, i1, 0]
         + (1 - tx) * ty * field[j1, i, 0] + tx * ty * field[j1, i1, 0])
    v = ((1 - tx) * (1 - ty) * field[j, i, 1] + tx * (1 - ty) * field[j, i1, 1]
         + (1 - tx) * ty * field[j1, i, 1] + tx * ty * field[j1, i1, 1])
    return u, v


@numba.njit(cache=True)
def interpolate(field, x0, y0, dx, dy, position):
    """Velocity [m/s] (N, 2) at ``position`` (N, 2) from a cell-centred field."""
    out = np.empty_like(position)
    for n in range(position.shape[0]):
        u, v = sample(field, x0, y0, dx, dy, position[n, 0], position[n, 1])
        out[n, 0] = u
        out[n, 1] = v
    return out


@numba.njit(cache=True)
def write_positions(field, x0, y0, dx, dy, position, slots, store_position, store_velocity):
    """Rows ``slots`` of a particle store get ``position`` (N, 2) in the plane (z = 0)
    and the field's velocity there (x and y) [m, m/s]."""
    for n in range(position.shape[0]):
        s = slots[n]
        u, v = sample(field, x0, y0, dx, dy, position[n, 0], position[n, 1])
        store_position[s, 0] = position[n, 0]
        store_position[s, 1] = position[n, 1]
        store_position[s, 2] = 0.0
        store_velocity[s, 0] = u
        store_velocity[s, 1] = v


@numba.njit(cache=True)
def advect(position, field, x0, y0, dx, dy, dt, substeps, x_lo, x_hi, y_lo):
    """Move ``position`` (N, 2) in place by the field over ``dt`` [s] (midpoint rule)."""
    h = dt / substeps
    for n in range(position.shape[0]):
        x = position[n, 0]
        y = position[n, 1]
        for _ in range(substeps):
            u, v = sample(field, x0, y0, dx, dy, x, y)
            um, vm = sample(field, x0, y0, dx, dy, x + 0.5 * h * u, y + 0.5 * h * v)
            x = min(max(x + h * um, x_lo), x_hi)
            y = max(y + h * vm, y_lo)
        position[n, 0] = x
        position[n, 1] = y
