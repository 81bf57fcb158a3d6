"""Nonsmooth (time-implicit) 2D DEM: velocity-level contact complementarity
solved by projected Gauss-Seidel (``DemConfig.method = "nonsmooth"``).

The paper's simulator (section "Simulator": AGX Dynamics, 11 ms steps, 100
projected Gauss-Seidel iterations) uses the nonsmooth DEM of Servin, Wang,
Lacoursiere and Bodin (2014), "Examining the smooth and nonsmooth discrete
element approaches to granular matter", Int. J. Numer. Meth. Engng 97:878:
contacts are constraints on the velocities at the end of the step rather
than springs integrated through the contact, so the step is bound by the
motion to resolve, not by the contact time. Same particle state, lists,
geometry and feeder as the explicit DEM (``kernels.py``).

Time stepping (step h, per contact c between disks i and j or disk i and a
wall; n from j to i, t = (-n_y, n_x); gap g = |x_i - x_j| - r_i - r_j):

1. Free velocities ``v* = v + h g_vec`` (gravity), ``w* = w``.
2. Contact velocities of the end-of-step state (as in ``kernels.py``):
   ``u_n = (v_i - v_j) . n``, ``u_t = (v_i - v_j) . t - (r_i w_i + r_j w_j)``,
   ``u_r = w_i - w_j``; contact impulses [N s] ``p_n`` along n, ``p_t``
   along t, rolling impulse ``p_r`` [N m s]; on i ``+p_n n + p_t t``, torque
   ``-r_i p_t + p_r``; on j the opposite force and the torque ``-r_j p_t - p_r``.
3. Normal complementarity, ``0 <= p_n  perp  u_n+ + b + s p_n >= 0``, with
   (Servin et al. 2014; the regularised, stabilised constraint of
   Lacoursiere's SPOOK stepper, here in its implicit-Euler form):

   * a gap that this step does not close (``g > 0`` and ``g + h u_n* > 0``):
     ``b = g / h``, ``s = 0`` (the disks may close the gap, not pass it);
   * an impact (``u_n* < -impact_speed``): Newton's impact law
     ``u_n+ >= -e u_n*``, i.e. ``b = e u_n*``, ``s = 0``;
   * otherwise (resting or slow contacts): ``b = g / (h + tau)`` for
     ``g <= 0`` (``g / h`` for a small positive gap) and the compliance
     ``s = epsilon / (h (h + tau))``, ``epsilon = 1 / k_n`` [m/N],
     ``tau = stabilization_steps h`` [s]. This is the implicit-Euler step of
     a spring-dashpot with stiffness k_n and damping tau k_n: at rest the
     overlap is F / k_n (as in the explicit DEM); a penetration beyond it is
     removed over ``1 + stabilization_steps`` steps (the stabilisation).

4. Coulomb friction ``|p_t| <= mu p_n`` with ``u_t+ = 0`` while sticking,
   rolling resistance ``|p_r| <= mu_r R_eff p_n`` with ``u_r+ = 0`` while
   not rolling (the plastic limit of the explicit DEM's rolling model,
   Ai et al. 2011; ``R_eff = r_i r_j / (r_i + r_j)``, ``r_i`` for a wall).
5. Projected Gauss-Seidel: contacts in a fixed order (pairs in list order,
   then wall contacts), each row solved for its impulse and projected on its
   bounds, velocities updated at once; ``solver_iterations`` sweeps at most,
   fewer when the largest velocity change of a sweep is below
   ``solver_tolerance`` [m/s]. With ``solver_relaxation`` omega != 1 the
   normal impulse's correction is scaled by omega before the projection:
   projected successive over-relaxation (C. W. Cryer 1971, "The solution of a
   quadratic programming problem using systematic overrelaxation", SIAM J.
   Control 9:385), which converges for 0 < omega < 2 on a symmetric positive
   definite contact matrix. On the diffusion-like load path of a tall pile
   Gauss-Seidel needs of the order of n^2 sweeps for n disks from top to floor,
   over-relaxation near its optimum 2 / (1 + sin(pi / n)) (D. M. Young 1971,
   "Iterative solution of large linear systems", chapter 6) of the order of n.
   Friction and rolling rows are not over-relaxed. Warm start: the impulses of the previous step
   (kept per list entry in ``hn, ht, hr``) are applied before the first
   sweep, except for impacting contacts.
6. Missed contacts: a pair (or disk and wall) whose gap was too wide to
   close at the disks' speeds before the solve (item 2 leaves it out) can
   still close when the solve speeds a disk up, e.g. a disk at rest struck
   by a column falling onto it. After the sweeps every list entry left out
   is checked with the end-of-step velocities (``g + h u_n+ < 0``: it would
   overlap); if any is, the step is solved again from the free velocities
   with those entries as rows (at most ``missed_contact_resolves`` times), so no
   contact in the lists is passed unseen. ``stats[4]`` counts these
   re-solves.
7. ``x += h v+``; the feeders and the blow-up guard as in the explicit DEM.

SPOOK: C. Lacoursiere (2007), "Ghosts and machines: regularized variational
methods for interactive simulations of multibodies with dry frictional
contacts", PhD thesis, Umea University; the form above is its implicit-Euler
reading (a stiff spring-dashpot solved at the end of the step), not its
exact constants.

Cohesion is not modelled here (``DemConfig`` refuses it with this method).
Deterministic: everything runs in one thread in a fixed order.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from surrogate.dem.config import GRAVITY
from surrogate.dem.kernels import (
    GUARD_NONE,
    HOT,
    P_G,
    P_MU,
    P_MUR,
    _closest_on_segment,
    feed,
    guard_scan,
)

# indices into the ``solver`` vector handed to ``run_steps``
S_EPS, S_TAU_STEPS, S_E, S_VIMP, S_ITER, S_TOL, S_RESOLVES, S_RELAX = range(8)
N_SOLVER = 8

N_STATS = 7
"""Length of the ``stats`` vector of ``run_steps``."""


def solver_params(cfg) -> np.ndarray:
    """The ``solver`` vector of a ``DemConfig`` (module docstring)."""
    solver = np.zeros(N_SOLVER)
    solver[S_EPS] = 1.0 / cfg.normal_stiffness
    solver[S_TAU_STEPS] = cfg.stabilization_steps
    solver[S_E] = cfg.restitution
    solver[S_VIMP] = cfg.impact_speed
    solver[S_ITER] = cfg.solver_iterations
    solver[S_TOL] = cfg.solver_tolerance
    solver[S_RESOLVES] = cfg.missed_contact_resolves
    solver[S_RELAX] = cfg.solver_relaxation
    return solver


RESIDUAL_WARNING = 0.1
"""A run's solver counts as unconverged when its steps' last sweep changed a
velocity by more than this fraction of ``g h`` on average (what gravity adds in
one step: 0.11 m/s at 11 ms). Measured on a settled 2,000-disk pile continued
3 s at 11 ms and 100 sweeps with the feeder shut (surrogate/dem/README.md,
"Solver convergence"): 0.0015 m/s at k_n = 4e7 N/m, where it rests, 0.089 m/s
at 1e10 N/m, where it creeps."""


def convergence(stats: np.ndarray, before: np.ndarray, dt: float, cfg) -> dict:
    """The solver's convergence between two readings of ``Dem.solver_stats``
    (``run_steps``' counters; ``before`` the earlier one) at the step ``dt`` [s]:
    steps, mean sweeps per step, the steps that ended unconverged (all
    ``solver_iterations`` sweeps used, the last one's largest velocity change
    still above ``solver_tolerance``), the mean of that last change over the
    steps [m/s], and ``converged``: that mean at most ``RESIDUAL_WARNING g dt``;
    None under over-relaxation (``solver_relaxation`` != 1), whose sweeps
    overshoot by design, so that the change of its last sweep does not measure
    how far it is from the solution. A pile whose Gauss-Seidel solver has not
    converged does not rest: it creeps."""
    delta = stats - before
    steps = int(delta[0])
    mean_change = float(delta[6] / steps) if steps else 0.0
    limit = RESIDUAL_WARNING * GRAVITY * dt
    return {
        "steps": steps,
        "sweeps_per_step": float(delta[1] / steps) if steps else 0.0,
        "solver_iterations": cfg.solver_iterations,
        "unconverged_steps": int(delta[5]),
        "mean_last_sweep_change_m_s": mean_change,
        "solver_tolerance_m_s": cfg.solver_tolerance,
        "residual_limit_m_s": limit,
        "converged": mean_change <= limit if cfg.solver_relaxation == 1.0 else None,
    }


@njit(inline="always", **HOT)
def _wall_offset(x, y, walls, w):
    """``(dx, dy, d)``: the offset [m] of the point (x, y) from its closest point
    on wall ``w``, and its length."""
    cx, cy = _closest_on_segment(x, y, walls[w, 0], walls[w, 1], walls[w, 2], walls[w, 3])
    dx = x - cx
    dy = y - cy
    return dx, dy, math.sqrt(dx * dx + dy * dy)


@njit(**HOT)
def _gather_contacts(h, pos, vel, omega, radius, inv_mass, inv_inertia, start, nbr, hn, ht, hr,
                     wall_start, wall, wall_hn, wall_ht, wall_hr, walls, solver, c_i, c_j, c_slot,
                     c_n, c_b, c_s, c_inv, c_pn, c_pt, c_pr, c_reff, pair_row, wall_row):
    """Fill the contact rows of this step (module docstring, items 2-3) and
    apply the warm start; returns the number of rows. ``c_slot`` is the list
    entry (pairs) or ``-1 - entry`` (walls); ``c_j`` is -1 for a wall.
    ``pair_row`` / ``wall_row`` per list entry: 1 to make it a row whatever its
    gap (a missed contact, item 6); on return 1 for every entry made a row, 0
    for those left out."""
    eps = solver[S_EPS]
    tau = solver[S_TAU_STEPS] * h
    e = solver[S_E]
    vimp = solver[S_VIMP]
    soft = eps / (h * (h + tau))
    n = pos.shape[0]
    speed = np.empty(n)
    for i in range(n):
        speed[i] = math.sqrt(vel[i, 0] * vel[i, 0] + vel[i, 1] * vel[i, 1])
    m = 0
    for i in range(n):
        ri = radius[i]
        for p in range(start[i], start[i + 1]):
            j = nbr[p]
            dx = pos[i, 0] - pos[j, 0]
            dy = pos[i, 1] - pos[j, 1]
            d = math.sqrt(dx * dx + dy * dy)
            rj = radius[j]
            g = d - ri - rj
            nx_ = dx / d
            ny_ = dy / d
            un = (vel[i, 0] - vel[j, 0]) * nx_ + (vel[i, 1] - vel[j, 1]) * ny_
            # pairs that cannot meet within the step at their speeds are left out (their
            # impulses forgotten); a column falling as one still has all its rows
            if (pair_row[p] == 0 and g > 0.0
                    and g > h * (speed[i] + speed[j]) + 0.05 * min(ri, rj)):
                hn[p] = 0.0
                ht[p] = 0.0
                hr[p] = 0.0
                continue
            pair_row[p] = 1
            c_i[m] = i
            c_j[m] = j
            c_slot[m] = p
            c_n[m, 0] = nx_
            c_n[m, 1] = ny_
            c_reff[m] = ri * rj / (ri + rj)
            c_inv[m, 0] = inv_mass[i] + inv_mass[j]
            c_inv[m, 1] = c_inv[m, 0] + ri * ri * inv_inertia[i] + rj * rj * inv_inertia[j]
            c_inv[m, 2] = inv_inertia[i] + inv_inertia[j]
            warm = _bias(g, un, h, tau, e, vimp, soft, c_b, c_s, m)
            c_pn[m] = hn[p] if warm else 0.0
            c_pt[m] = ht[p] if warm else 0.0
            c_pr[m] = hr[p] if warm else 0.0
            m += 1
    for i in range(n):
        ri = radius[i]
        for p in range(wall_start[i], wall_start[i + 1]):
            dx, dy, d = _wall_offset(pos[i, 0], pos[i, 1], walls, wall[p])
            g = d - ri
            nx_ = dx / d
            ny_ = dy / d
            un = vel[i, 0] * nx_ + vel[i, 1] * ny_
            if wall_row[p] == 0 and g > 0.0 and g > h * speed[i] + 0.05 * ri:
                wall_hn[p] = 0.0
                wall_ht[p] = 0.0
                wall_hr[p] = 0.0
                continue
            wall_row[p] = 1
            c_i[m] = i
            c_j[m] = -1
            c_slot[m] = -1 - p
            c_n[m, 0] = nx_
            c_n[m, 1] = ny_
            c_reff[m] = ri
            c_inv[m, 0] = inv_mass[i]
            c_inv[m, 1] = inv_mass[i] + ri * ri * inv_inertia[i]
            c_inv[m, 2] = inv_inertia[i]
            warm = _bias(g, un, h, tau, e, vimp, soft, c_b, c_s, m)
            c_pn[m] = wall_hn[p] if warm else 0.0
            c_pt[m] = wall_ht[p] if warm else 0.0
            c_pr[m] = wall_hr[p] if warm else 0.0
            m += 1
    for c in range(m):
        _apply(c_i[c], c_j[c], c_n[c, 0], c_n[c, 1], c_pn[c], c_pt[c], c_pr[c], radius, vel,
               omega, inv_mass, inv_inertia)
    return m


@njit(inline="always", **HOT)
def _bias(g, un, h, tau, e, vimp, soft, c_b, c_s, m):
    """Bias and compliance of row ``m`` (module docstring, item 3); False for an impact
    (no warm start)."""
    if g > 0.0 and g + h * un > 0.0:
        c_b[m] = g / h
        c_s[m] = 0.0
        return True
    if un < -vimp:
        c_b[m] = e * un
        c_s[m] = 0.0
        return False
    if g > 0.0:
        c_b[m] = g / h
        c_s[m] = 0.0
    else:
        c_b[m] = g / (h + tau)
        c_s[m] = soft
    return True


@njit(inline="always", **HOT)
def _apply(i, j, nx_, ny_, dpn, dpt, dpr, radius, vel, omega, inv_mass, inv_inertia):
    """Velocity change of an impulse change (dpn, dpt, dpr) of one contact."""
    fx = dpn * nx_ - dpt * ny_
    fy = dpn * ny_ + dpt * nx_
    vel[i, 0] += fx * inv_mass[i]
    vel[i, 1] += fy * inv_mass[i]
    omega[i] += (-radius[i] * dpt + dpr) * inv_inertia[i]
    if j >= 0:
        vel[j, 0] -= fx * inv_mass[j]
        vel[j, 1] -= fy * inv_mass[j]
        omega[j] += (-radius[j] * dpt - dpr) * inv_inertia[j]


@njit(inline="always", **HOT)
def _relative(i, j, nx_, ny_, radius, vel, omega):
    """(u_n, u_t) of one contact."""
    if j >= 0:
        dvx = vel[i, 0] - vel[j, 0]
        dvy = vel[i, 1] - vel[j, 1]
        spin = radius[i] * omega[i] + radius[j] * omega[j]
    else:
        dvx = vel[i, 0]
        dvy = vel[i, 1]
        spin = radius[i] * omega[i]
    return dvx * nx_ + dvy * ny_, -dvx * ny_ + dvy * nx_ - spin


@njit(**HOT)
def solve_pgs(m, c_i, c_j, c_n, c_b, c_s, c_inv, c_pn, c_pt, c_pr, c_reff, radius, vel, omega,
              inv_mass, inv_inertia, mu, mur, iterations, tolerance, relaxation):
    """Projected Gauss-Seidel over the ``m`` rows (module docstring, item 5);
    returns ``(sweeps, largest velocity change of the last sweep [m/s])``."""
    change = 0.0
    sweeps = 0
    for sweep in range(iterations):
        change = 0.0
        for c in range(m):
            i = c_i[c]
            j = c_j[c]
            nx_ = c_n[c, 0]
            ny_ = c_n[c, 1]
            un, ut = _relative(i, j, nx_, ny_, radius, vel, omega)
            s = c_s[c]
            pn = c_pn[c] - relaxation * (un + c_b[c] + s * c_pn[c]) / (c_inv[c, 0] + s)
            if pn < 0.0:
                pn = 0.0
            dpn = pn - c_pn[c]
            c_pn[c] = pn
            # a normal impulse leaves u_t alone (n is normal to t and passes the centres)
            limit = mu * pn
            pt = min(max(c_pt[c] - ut / c_inv[c, 1], -limit), limit)
            dpt = pt - c_pt[c]
            c_pt[c] = pt
            _apply(i, j, nx_, ny_, dpn, dpt, 0.0, radius, vel, omega, inv_mass, inv_inertia)
            ur = omega[i] - omega[j] if j >= 0 else omega[i]
            rlimit = mur * c_reff[c] * pn
            pr = min(max(c_pr[c] - ur / c_inv[c, 2], -rlimit), rlimit)
            dpr = pr - c_pr[c]
            c_pr[c] = pr
            _apply(i, j, nx_, ny_, 0.0, 0.0, dpr, radius, vel, omega, inv_mass, inv_inertia)
            dv = max(abs(dpn) * c_inv[c, 0], abs(dpt) * c_inv[c, 1])
            if dv > change:
                change = dv
        sweeps = sweep + 1
        if change < tolerance:
            break
    return sweeps, change


@njit(**HOT)
def _mark_missed(h, pos, vel, radius, start, nbr, wall_start, wall, walls, pair_row, wall_row):
    """Mark the list entries left out of the rows that the end-of-step
    velocities would make overlap (module docstring, item 6) with
    ``pair_row`` / ``wall_row`` = 1; returns how many."""
    missed = 0
    for i in range(pos.shape[0]):
        ri = radius[i]
        for p in range(start[i], start[i + 1]):
            if pair_row[p] != 0:
                continue
            j = nbr[p]
            dx = pos[i, 0] - pos[j, 0]
            dy = pos[i, 1] - pos[j, 1]
            d = math.sqrt(dx * dx + dy * dy)
            un = ((vel[i, 0] - vel[j, 0]) * dx + (vel[i, 1] - vel[j, 1]) * dy) / d
            if d - ri - radius[j] + h * un < 0.0:
                pair_row[p] = 1
                missed += 1
        for p in range(wall_start[i], wall_start[i + 1]):
            if wall_row[p] != 0:
                continue
            dx, dy, d = _wall_offset(pos[i, 0], pos[i, 1], walls, wall[p])
            if d - ri + h * (vel[i, 0] * dx + vel[i, 1] * dy) / d < 0.0:
                wall_row[p] = 1
                missed += 1
    return missed


@njit(**HOT)
def run_steps(n_steps, dt, time, pos, vel, omega, radius, inv_mass, inv_inertia, start, nbr, hn,
              ht, hr, wall_start, wall, wall_hn, wall_ht, wall_hr, walls, params, solver,
              ref_pos, half_skin, candidates, outlet_lo, outlet_hi, zone_top, rates, credits,
              credit_cap, tracked_mass, removed, speed_limit, box, stats):
    """Advance up to ``n_steps`` nonsmooth steps of ``dt`` [s] from ``time`` [s].

    Stops early as ``kernels.run_steps`` does (list rebuild, feeder removal,
    blow-up guard), with the same return tuple. The lists must hold every
    pair a disk can reach in a step: a rebuild is asked for when a disk's
    displacement since the build plus its reach in the next step,
    ``h (|v| + g h)``, exceeds ``half_skin``. ``stats`` (``N_STATS``)
    accumulates ``[steps, sweeps, rows, last residual velocity change [m/s],
    re-solves for missed contacts, steps that ended unconverged (all sweeps used,
    the last one's change above the tolerance), sum over the steps of their last
    sweep's largest velocity change [m/s]]``.
    """
    n = pos.shape[0]
    g = params[P_G]
    mu = params[P_MU]
    mur = params[P_MUR]
    iterations = int(solver[S_ITER])
    tolerance = solver[S_TOL]
    resolves = int(solver[S_RESOLVES])
    relaxation = solver[S_RELAX]
    speed2 = speed_limit * speed_limit
    capacity = nbr.shape[0] + wall.shape[0]
    c_i = np.empty(capacity, np.int64)
    c_j = np.empty(capacity, np.int64)
    c_slot = np.empty(capacity, np.int64)
    c_n = np.empty((capacity, 2))
    c_b = np.empty(capacity)
    c_s = np.empty(capacity)
    c_inv = np.empty((capacity, 3))
    c_pn = np.empty(capacity)
    c_pt = np.empty(capacity)
    c_pr = np.empty(capacity)
    c_reff = np.empty(capacity)
    pair_row = np.zeros(nbr.shape[0], np.int8)
    wall_row = np.zeros(wall.shape[0], np.int8)
    free_vel = np.empty_like(vel)
    free_omega = np.empty_like(omega)
    n_removed = 0
    for step in range(n_steps):
        for i in range(n):
            vel[i, 1] -= g * dt
        free_vel[:] = vel
        free_omega[:] = omega
        pair_row[:] = 0
        wall_row[:] = 0
        for attempt in range(resolves + 1):
            if attempt:
                vel[:] = free_vel
                omega[:] = free_omega
                stats[4] += 1.0
            m = _gather_contacts(dt, pos, vel, omega, radius, inv_mass, inv_inertia, start, nbr,
                                 hn, ht, hr, wall_start, wall, wall_hn, wall_ht, wall_hr, walls,
                                 solver, c_i, c_j, c_slot, c_n, c_b, c_s, c_inv, c_pn, c_pt, c_pr,
                                 c_reff, pair_row, wall_row)
            sweeps, change = solve_pgs(m, c_i, c_j, c_n, c_b, c_s, c_inv, c_pn, c_pt, c_pr,
                                       c_reff, radius, vel, omega, inv_mass, inv_inertia, mu,
                                       mur, iterations, tolerance, relaxation)
            stats[1] += sweeps
            if attempt == resolves or _mark_missed(dt, pos, vel, radius, start, nbr,
                                                       wall_start, wall, walls, pair_row,
                                                       wall_row) == 0:
                break
        for c in range(m):
            p = c_slot[c]
            if p >= 0:
                hn[p] = c_pn[c]
                ht[p] = c_pt[c]
                hr[p] = c_pr[c]
            else:
                wall_hn[-1 - p] = c_pn[c]
                wall_ht[-1 - p] = c_pt[c]
                wall_hr[-1 - p] = c_pr[c]
        stats[0] += 1.0
        stats[2] += m
        stats[3] = change
        if change >= tolerance:
            stats[5] += 1.0
        stats[6] += change
        moved = False
        for i in range(n):
            pos[i, 0] += vel[i, 0] * dt
            pos[i, 1] += vel[i, 1] * dt
            dx = pos[i, 0] - ref_pos[i, 0]
            dy = pos[i, 1] - ref_pos[i, 1]
            reach = math.sqrt(dx * dx + dy * dy) + dt * (
                math.sqrt(vel[i, 0] * vel[i, 0] + vel[i, 1] * vel[i, 1]) + g * dt)
            if reach > half_skin:
                moved = True
        time += dt
        bad_row, bad_kind = guard_scan(pos, vel, speed2, box)
        if bad_kind != GUARD_NONE:
            return step + 1, time, n_removed, moved, bad_row, bad_kind
        n_removed = feed(dt, pos, candidates, outlet_lo, outlet_hi, zone_top, rates, credits,
                         credit_cap, tracked_mass, removed, n_removed)
        if n_removed > 0 or moved:
            return step + 1, time, n_removed, moved, -1, GUARD_NONE
    return n_steps, time, n_removed, False, -1, GUARD_NONE
