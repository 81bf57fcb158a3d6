"""Mass-conserving bulk transport: the predicted field projected on the grid.

Source: the pressure projection of incompressible flow (Chorin 1968,
"Numerical solution of the Navier-Stokes equations", Math. Comp. 22, 745-762)
on the staggered (MAC) grid of Harlow and Welch (1965, Phys. Fluids 8,
2182-2189), and the face-velocity interpolation of semi-analytical particle
tracking (Pollock 1988, "Semianalytical computation of path lines for
finite-difference models", Ground Water 26, 743-750), in which the
interpolated field is divergence free inside every cell whose face fluxes
balance.

Why: the ridge regression of the paper's ROM (Wallin and Servin 2021)
predicts a velocity field that is not mass-conserving (the fitted field
converges towards the funnel at every depth). Advected by it, the bulk
compacts, and the column re-packing that undoes this scatters particles
about the mean flow. Projected, the field keeps the settled bulk at its
density by itself.

Equations (2-D plane, x horizontal, y up; the settled bulk has the uniform
areal density rho_A [kg/m^2], ``Container.areal_density``):

- In the settled bulk, d(rho_A)/dt = 0, so div(rho_A v) = rho_A div v = s,
  with the sink s only at the feeder: the floor faces over the opening carry
  the outflow q_out / rho_A [m^2/s] (q_out the discharge rate [kg/s]), shared
  across the opening in proportion to ``draw`` (the predicted field's
  downward speed there; evenly when it has none). Walls and the rest of the
  floor carry no flux. The inflow lands on the free surface, where nothing
  is imposed.
- Face velocities U (ny, nx + 1) [m/s] on the vertical faces and V
  (ny + 1, nx) on the horizontal ones are the means of the two cell-centred
  predicted values beside them. A cell is bulk when it holds at least
  ``fill`` times the mass of a full cell (rho_A dx dy); the others (the
  surface cells, partly filled, and the air) are the free surface, where
  the potential is 0 (Dirichlet; likewise above the grid).
- The potential phi [m^2/s] solves, on the bulk cells, the 5-point
  Poisson equation lap(phi) = div(U, V) (faces to walls and floor: no
  correction, Neumann), by Jacobi-preconditioned conjugate gradients to a
  residual of ``TOLERANCE`` of the right-hand side; every face beside a
  bulk cell is corrected, U -= d(phi)/dx, V -= d(phi)/dy. The discrete
  divergence of every bulk cell is then 0 (to the solver's tolerance).
- ``free_surface="potential"`` is the above: the free surface takes up any
  imbalance where it lies. ``free_surface="flux"`` (``RomStorage``'s
  default transport "balanced") holds the volume of the bulk over the
  feeder (its connected bulk cells): its surface faces carry the predicted
  flux, the inward part scaled by (Q_out + F_out) / F_in, with Q_out the
  feeder's outflow through its floor and F_in, F_out [m^2/s] the predicted
  inward and outward flux through its surface, so what the surface feeds
  into the bulk is what the feeder and the outward faces take; the Poisson
  problem is then Neumann on that component (one cell pinned at phi = 0).
  Material thus enters the bulk where the prediction has it enter, at the
  rate the feeder draws it; the surface cells (fed by the inflow) sink or
  rise by the difference.
- Particles move by the Pollock interpolation: inside a cell, u is linear
  in x between the cell's two vertical faces and v linear in y between its
  two horizontal faces, so du/dx + dv/dy is the cell's discrete divergence:
  0 in the bulk. Integrated by the explicit midpoint rule (second order) in
  substeps; positions are then kept in the container (walls, floor).

Parameters (of ``project``): ``fill`` [-] (default ``FILL`` = 0.9): the
least fill of a bulk cell; ``free_surface`` (default "potential", above).
"""

from __future__ import annotations

import numba
import numpy as np

FILL = 0.9
"""Least fraction of a full cell's mass (rho_A dx dy) that makes a cell bulk [-]."""

TOLERANCE = 1e-10
"""Relative residual at which the conjugate gradients stop [-]."""


@numba.njit(cache=True)
def _solve(rhs, unknown, openx, openy, dx2, dy2, tolerance, max_iterations):
    """phi (0 off the ``unknown`` cells and above the grid) with -lap(phi) = rhs
    on them over their open faces (``openx`` (ny, nx + 1), ``openy``
    (ny + 1, nx); a closed face carries no correction), by
    Jacobi-preconditioned conjugate gradients; returns ``(phi, iterations)``."""
    ny, nx = rhs.shape
    number = np.full(ny * nx, -1, np.int64)
    cells = np.flatnonzero(unknown.ravel())
    m = cells.size
    for k in range(m):
        number[cells[k]] = k
    # per unknown: its open faces' neighbours (index among the unknowns, or -1
    # for a neighbour at phi = 0) and weights; the diagonal
    neighbour = np.full((m, 4), -1, np.int64)
    weight = np.zeros((m, 4))
    diag = np.empty(m)
    r = np.empty(m)
    for k in range(m):
        j, i = divmod(cells[k], nx)
        d = 0.0
        if openy[j + 1, i]:
            d += 1.0 / dy2
            if j < ny - 1:
                neighbour[k, 0] = number[(j + 1) * nx + i]
                weight[k, 0] = 1.0 / dy2
        if openy[j, i]:
            d += 1.0 / dy2
            neighbour[k, 1] = number[(j - 1) * nx + i]
            weight[k, 1] = 1.0 / dy2
        if openx[j, i]:
            d += 1.0 / dx2
            neighbour[k, 2] = number[j * nx + i - 1]
            weight[k, 2] = 1.0 / dx2
        if openx[j, i + 1]:
            d += 1.0 / dx2
            neighbour[k, 3] = number[j * nx + i + 1]
            weight[k, 3] = 1.0 / dx2
        diag[k] = d if d > 0.0 else 1.0
        r[k] = rhs[j, i]
    x = np.zeros(m)
    z = r / diag
    p = z.copy()
    ap = np.empty(m)
    rz = (r * z).sum()
    norm = (r * r).sum()
    phi = np.zeros((ny, nx))
    iterations = 0
    if norm > 0.0:
        for it in range(max_iterations):
            pap = 0.0
            for k in range(m):
                s = diag[k] * p[k]
                for e in range(4):
                    n = neighbour[k, e]
                    if n >= 0:
                        s -= weight[k, e] * p[n]
                ap[k] = s
                pap += p[k] * s
            iterations = it + 1
            if pap <= 0.0:
                break
            step = rz / pap
            rr = 0.0
            for k in range(m):
                x[k] += step * p[k]
                r[k] -= step * ap[k]
                rr += r[k] * r[k]
            if rr <= tolerance * tolerance * norm:
                break
            rz_new = 0.0
            for k in range(m):
                z[k] = r[k] / diag[k]
                rz_new += r[k] * z[k]
            beta = rz_new / rz
            rz = rz_new
            for k in range(m):
                p[k] = z[k] + beta * p[k]
    for k in range(m):
        j, i = divmod(cells[k], nx)
        phi[j, i] = x[k]
    return phi, iterations


@numba.njit(cache=True)
def _balance(u, v, bulk, openx, openy, unknown, dx, dy):
    """``free_surface="flux"``: the bulk component over the feeder (the one whose
    floor faces carry the most outflow) keeps its volume. Its surface faces
    (to non-bulk cells and above the grid) are closed to the correction and
    carry the predicted flux, the inward part scaled so that what enters
    equals what leaves (through the floor and the outward surface faces); one
    cell of it (the highest, then leftmost) is pinned at phi = 0 (the Neumann
    problem fixes phi up to a constant). Returns False, changing nothing, if
    there is no such component or no inward flux to scale."""
    ny, nx = bulk.shape
    label = np.full((ny, nx), -1, np.int64)
    stack = np.empty(ny * nx, np.int64)
    count = 0
    for start in range(ny * nx):
        if not bulk.ravel()[start] or label.ravel()[start] >= 0:
            continue
        top = 0
        stack[0] = start
        label.ravel()[start] = count
        while top >= 0:
            c = stack[top]
            top -= 1
            j, i = divmod(c, nx)
            for dj, di in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                jj, ii = j + dj, i + di
                if 0 <= jj < ny and 0 <= ii < nx and bulk[jj, ii] and label[jj, ii] < 0:
                    label[jj, ii] = count
                    top += 1
                    stack[top] = jj * nx + ii
        count += 1
    if count == 0:
        return False
    drained = np.zeros(count)
    for i in range(nx):
        if label[0, i] >= 0:
            drained[label[0, i]] += -v[0, i] * dx
    target = int(np.argmax(drained))
    if drained[target] <= 0.0:
        return False
    inward, outward = 0.0, 0.0
    for j in range(ny):
        for i in range(nx):
            if label[j, i] != target:
                continue
            # inward flux through each surface face (positive into the cell)
            if j == ny - 1 or not bulk[j + 1, i]:
                f = -v[j + 1, i] * dx
                inward += max(f, 0.0)
                outward += max(-f, 0.0)
            if j > 0 and not bulk[j - 1, i]:
                f = v[j, i] * dx
                inward += max(f, 0.0)
                outward += max(-f, 0.0)
            if i > 0 and not bulk[j, i - 1]:
                f = u[j, i] * dy
                inward += max(f, 0.0)
                outward += max(-f, 0.0)
            if i < nx - 1 and not bulk[j, i + 1]:
                f = -u[j, i + 1] * dy
                inward += max(f, 0.0)
                outward += max(-f, 0.0)
    if inward <= 0.0:
        return False
    scale = (drained[target] + outward) / inward
    pin = -1
    for j in range(ny):
        for i in range(nx):
            if label[j, i] != target:
                continue
            pin = j * nx + i if pin < 0 or j > pin // nx else pin
            if j == ny - 1 or not bulk[j + 1, i]:
                if -v[j + 1, i] > 0.0:
                    v[j + 1, i] *= scale
                openy[j + 1, i] = False
            if j > 0 and not bulk[j - 1, i]:
                if v[j, i] > 0.0:
                    v[j, i] *= scale
                openy[j, i] = False
            if i > 0 and not bulk[j, i - 1]:
                if u[j, i] > 0.0:
                    u[j, i] *= scale
                openx[j, i] = False
            if i < nx - 1 and not bulk[j, i + 1]:
                if -u[j, i + 1] > 0.0:
                    u[j, i + 1] *= scale
                openx[j, i + 1] = False
    jp, ip = divmod(pin, nx)
    unknown[jp, ip] = False
    return True


@numba.njit(cache=True)
def _faces(field, outflow):
    """Face velocities (U, V) from a cell-centred field (ny, nx, 2): interior faces
    the mean of their two cells, walls 0, floor ``outflow`` (nx,) [m/s, up
    positive], the top of the grid the top row's value."""
    ny, nx = field.shape[0], field.shape[1]
    u = np.zeros((ny, nx + 1))
    v = np.zeros((ny + 1, nx))
    for j in range(ny):
        for i in range(1, nx):
            u[j, i] = 0.5 * (field[j, i - 1, 0] + field[j, i, 0])
    for i in range(nx):
        v[0, i] = outflow[i]
        for j in range(1, ny):
            v[j, i] = 0.5 * (field[j - 1, i, 1] + field[j, i, 1])
        v[ny, i] = field[ny - 1, i, 1]
    return u, v


@numba.njit(cache=True)
def _correct(u, v, phi, openx, openy, dx, dy):
    """U -= d(phi)/dx, V -= d(phi)/dy on the open faces (phi 0 above the grid)."""
    ny, nx = phi.shape
    for j in range(ny):
        for i in range(1, nx):
            if openx[j, i]:
                u[j, i] -= (phi[j, i] - phi[j, i - 1]) / dx
    for i in range(nx):
        for j in range(1, ny + 1):
            if openy[j, i]:
                above = phi[j, i] if j < ny else 0.0
                v[j, i] -= (above - phi[j - 1, i]) / dy


@numba.njit(cache=True)
def divergence(u, v, dx, dy):
    """Discrete divergence per cell (ny, nx) [1/s] of face velocities."""
    ny, nx = v.shape[0] - 1, u.shape[1] - 1
    out = np.empty((ny, nx))
    for j in range(ny):
        for i in range(nx):
            out[j, i] = (u[j, i + 1] - u[j, i]) / dx + (v[j + 1, i] - v[j, i]) / dy
    return out


def outlet_faces(grid, container, discharge_rate: float, draw=None) -> np.ndarray:
    """Velocity [m/s] (nx,) of the floor faces (up positive): the outflow
    q_out / rho_A shared over the opening by each face's overlap with it times
    ``draw`` (nx,) [any unit, >= 0; default or all 0: evenly]."""
    left = grid.x_min + np.arange(grid.nx) * grid.dx
    lo = container.outlet_x - 0.5 * container.outlet_width
    hi = container.outlet_x + 0.5 * container.outlet_width
    overlap = np.clip(np.minimum(left + grid.dx, hi) - np.maximum(left, lo), 0.0, None)
    if container.outlet_width <= 0:  # a point outlet: the face under it
        index = min(max(int((container.outlet_x - grid.x_min) / grid.dx), 0), grid.nx - 1)
        overlap[index] = grid.dx
    share = overlap if draw is None else overlap * np.maximum(np.asarray(draw, float), 0.0)
    if share.sum() <= 0:
        share = overlap
    flux = discharge_rate / container.areal_density  # [m^2/s]
    return -flux * share / (share.sum() * grid.dx)


FREE_SURFACES = ("potential", "flux")
"""Accepted values of ``project(free_surface=...)``."""


def project(field: np.ndarray, mass: np.ndarray, grid, container, discharge_rate: float,
            draw=None, fill: float = FILL, free_surface: str = "potential",
            max_iterations: int = 5000):
    """The mass-conserving face velocities ``(U (ny, nx + 1), V (ny + 1, nx))``
    [m/s] nearest to the cell-centred ``field`` (ny, nx, 2) [m/s] for the mass
    field ``mass`` (ny, nx) [kg] and ``discharge_rate`` [kg/s] (module
    docstring; ``draw``: see ``outlet_faces``; ``free_surface``: see
    ``_balance``)."""
    if free_surface not in FREE_SURFACES:
        raise ValueError(f"free_surface: one of {FREE_SURFACES}, got {free_surface!r}")
    field = np.ascontiguousarray(field, dtype=np.float64)
    bulk = np.asarray(mass, dtype=np.float64) >= fill * container.areal_density * grid.dx * grid.dy
    u, v = _faces(field, outlet_faces(grid, container, discharge_rate, draw))
    openx = np.ones((grid.ny, grid.nx + 1), dtype=np.bool_)
    openx[:, 0] = openx[:, -1] = False  # walls
    openy = np.ones((grid.ny + 1, grid.nx), dtype=np.bool_)
    openy[0] = False  # floor
    unknown = bulk.copy()
    if free_surface == "flux":
        _balance(u, v, bulk, openx, openy, unknown, grid.dx, grid.dy)
    rhs = -divergence(u, v, grid.dx, grid.dy)
    phi, _ = _solve(rhs, unknown, openx, openy, grid.dx ** 2, grid.dy ** 2, TOLERANCE,
                    max_iterations)
    _correct(u, v, phi, openx, openy, grid.dx, grid.dy)
    return u, v


@numba.njit(cache=True)
def centred(u, v):
    """Cell-centred field (ny, nx, 2) [m/s]: the mean of each cell's two faces per axis."""
    ny, nx = v.shape[0] - 1, u.shape[1] - 1
    out = np.empty((ny, nx, 2))
    for j in range(ny):
        for i in range(nx):
            out[j, i, 0] = 0.5 * (u[j, i] + u[j, i + 1])
            out[j, i, 1] = 0.5 * (v[j, i] + v[j + 1, i])
    return out


@numba.njit(cache=True, inline="always")
def sample_faces(u, v, x0, y0, dx, dy, x, y):
    """Velocity at (x, y) by the Pollock interpolation (module docstring); outside
    the grid the nearest cell's edge value."""
    ny, nx = v.shape[0] - 1, u.shape[1] - 1
    fx = (x - x0) / dx
    fy = (y - y0) / dy
    i = min(max(int(np.floor(fx)), 0), nx - 1)
    j = min(max(int(np.floor(fy)), 0), ny - 1)
    tx = min(max(fx - i, 0.0), 1.0)
    ty = min(max(fy - j, 0.0), 1.0)
    return ((1.0 - tx) * u[j, i] + tx * u[j, i + 1], (1.0 - ty) * v[j, i] + ty * v[j + 1, i])


@numba.njit(cache=True)
def advect_faces(position, u, v, x0, y0, dx, dy, dt, substeps, x_lo, x_hi, y_lo):
    """Move ``position`` (N, 2) in place by the face field over ``dt`` [s]
    (midpoint rule, ``substeps`` equal substeps), then keep it in x in
    [x_lo, x_hi], y >= y_lo [m]."""
    h = dt / substeps
    for n in range(position.shape[0]):
        x = position[n, 0]
        y = position[n, 1]
        for _ in range(substeps):
            a, b = sample_faces(u, v, x0, y0, dx, dy, x, y)
            am, bm = sample_faces(u, v, x0, y0, dx, dy, x + 0.5 * h * a, y + 0.5 * h * b)
            x = min(max(x + h * am, x_lo), x_hi)
            y = max(y + h * bm, y_lo)
        position[n, 0] = x
        position[n, 1] = y
