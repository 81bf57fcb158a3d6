"""Numba kernels of the 2D DEM: neighbour lists, contact forces, integration, feeder.

Everything that runs every step lives here and is compiled with
``numba.njit(cache=True)``; the Python side (``simulation.py``) only calls
``run_steps`` for a chunk of steps and handles the rare events (list rebuild,
removal of a discharged disk, emission).

Data layout (structure of arrays, N disks, row i):
``pos`` (N, 2) [m], ``vel`` (N, 2) [m/s], ``omega`` (N,) [rad/s],
``radius`` (N,) [m], ``inv_mass`` (N,) [1/kg], ``inv_inertia`` (N,)
[1/(kg m^2)], ``body_mass`` (N,) [kg].

Pair list (half Verlet list in CSR form): the neighbours j > i of disk i
within ``r_i + r_j + skin`` are ``nbr[start[i]:start[i+1]]`` in increasing j;
``ht[k]`` is the tangential spring elongation [m] and ``hr[k]`` the
rolling spring angle [rad] of pair k (zero when not in contact).
Wall list: the same for disk-segment pairs (``wall_start``, ``wall``,
``wall_ht``, ``wall_hr``), segments as rows ``(ax, ay, bx, by)``.

Contact law (pair i, j; n the unit vector from j to i, t = (-n_y, n_x)):

* overlap ``delta = r_i + r_j - |x_i - x_j|``, normal velocity
  ``v_n = (v_i - v_j) . n`` (< 0 approaching),
  ``F_n = max(k_n delta - c_n v_n, 0) - F_coh`` with
  ``c_n = 2 zeta sqrt(k_n m_eff)``, ``m_eff = m_i m_j / (m_i + m_j)``;
* tangential slip velocity ``v_t = (v_i - v_j) . t - (r_i w_i + r_j w_j)``,
  spring ``xi += v_t dt``, ``F_t = -k_t xi - c_t v_t`` with
  ``c_t = 2 zeta sqrt(k_t m_eff)``; if ``|F_t| > mu F_n+`` then
  ``F_t = sign(F_t) mu F_n+`` and ``xi = -F_t / k_t`` (sliding), where
  ``F_n+ = max(k_n delta - c_n v_n, 0)``;
* rolling angle ``theta += (w_i - w_j) dt``,
  ``M_r = -k_r theta - c_r (w_i - w_j)`` with ``k_r = 2.25 k_n mu_r^2 R_eff^2``,
  ``R_eff = r_i r_j / (r_i + r_j)``, ``c_r = 2 zeta sqrt(k_r I_eff)``,
  ``I_eff = I_i I_j / (I_i + I_j)``, capped at ``mu_r R_eff F_n+`` (then
  ``theta = -M_r / k_r``) (Ai et al. 2011, Powder Technol. 206:269, model C);
* force on i ``F_n n + F_t t``, torque on i ``-r_i F_t + M_r``; on j the
  opposite force and the torque ``-r_j F_t - M_r``.

Walls are the same law with ``m_eff = m_i``, ``R_eff = r_i`` and a static
wall. Integration: symplectic (semi-implicit) Euler,
``v += (F/m + g) dt; x += v dt; w += (M/I) dt``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from cosim.numerics import HOT_JIT

# fastmath (off with MINETWIN_REPRODUCIBLE=1, cosim.numerics) lets LLVM reorder
# float arithmetic: the same on every run of one machine, so restarts stay bit for
# bit, but not across instruction sets. error_model="numpy" drops the zero-division
# checks (distances are > 0 for every overlapping pair that reaches a division).
HOT = HOT_JIT

# indices into the ``params`` vector handed to the kernels
P_KN, P_KT, P_CN, P_CT, P_MU, P_MUR, P_KR, P_COH, P_G = range(9)
N_PARAMS = 9


def contact_params(cfg, gravity: float) -> np.ndarray:
    """The ``params`` vector of a ``DemConfig`` (contact law above) and ``gravity`` [m/s^2]."""
    zeta = cfg.damping_ratio
    kn = cfg.normal_stiffness
    kt = cfg.tangential_stiffness
    mur = cfg.rolling_resistance
    params = np.zeros(N_PARAMS)
    params[P_KN] = kn
    params[P_KT] = kt
    params[P_CN] = 2.0 * zeta * math.sqrt(kn)
    params[P_CT] = 2.0 * zeta * math.sqrt(kt)
    params[P_MU] = cfg.friction
    params[P_MUR] = mur
    params[P_KR] = 2.25 * kn * mur * mur
    params[P_COH] = cfg.cohesion
    params[P_G] = gravity
    return params


@njit(cache=True)
def _cell_grid(pos, cell_size):
    """Counting sort of disks into square cells; returns the grid description."""
    n = pos.shape[0]
    xmin = pos[0, 0]
    xmax = pos[0, 0]
    ymin = pos[0, 1]
    ymax = pos[0, 1]
    for i in range(1, n):
        xmin = min(xmin, pos[i, 0])
        xmax = max(xmax, pos[i, 0])
        ymin = min(ymin, pos[i, 1])
        ymax = max(ymax, pos[i, 1])
    # a scattered (e.g. exploding) system must not allocate a huge grid
    max_cells = 4 * n + 64
    while True:
        nx = int((xmax - xmin) / cell_size) + 1
        ny = int((ymax - ymin) / cell_size) + 1
        if nx * ny <= max_cells:
            break
        cell_size *= 1.5
    cell_of = np.empty(n, dtype=np.int64)
    count = np.zeros(nx * ny + 1, dtype=np.int64)
    for i in range(n):
        cx = int((pos[i, 0] - xmin) / cell_size)
        cy = int((pos[i, 1] - ymin) / cell_size)
        c = cy * nx + cx
        cell_of[i] = c
        count[c + 1] += 1
    for c in range(nx * ny):
        count[c + 1] += count[c]
    fill = count[:-1].copy()
    members = np.empty(n, dtype=np.int64)
    for i in range(n):
        c = cell_of[i]
        members[fill[c]] = i
        fill[c] += 1
    return xmin, ymin, cell_size, nx, ny, count, members


@njit(cache=True)
def _doubled(values, used):
    """``values`` with twice the room, its first ``used`` entries kept (CSR growth)."""
    grown = np.empty(2 * values.shape[0], dtype=values.dtype)
    grown[:used] = values[:used]
    return grown


@njit(cache=True)
def build_pair_list(pos, radius, skin, old_start, old_nbr, old_ht, old_hr, old_hn, new_to_old):
    """Half Verlet list (CSR, neighbours sorted) with contact history carried
    over (``ht``, ``hr``, ``hn``: three values per pair; the explicit DEM uses
    the first two, the nonsmooth one all three).

    ``new_to_old[i]`` is the row disk i had when the old list was built
    (-1 for a new disk); the mapping must be increasing where defined, so
    the old list of a disk is sorted in the same order as the new one.
    """
    n = pos.shape[0]
    start = np.zeros(n + 1, dtype=np.int64)
    nbr = np.empty(8 * n + 16, dtype=np.int64)
    if n == 0:
        return start, nbr[:0], np.zeros(0), np.zeros(0), np.zeros(0)
    rmax = radius.max()
    xmin, ymin, cs, nx, ny, cstart, members = _cell_grid(pos, 2.0 * rmax + skin)
    k = 0
    for i in range(n):
        cx = int((pos[i, 0] - xmin) / cs)
        cy = int((pos[i, 1] - ymin) / cs)
        first = k
        for gy in range(max(cy - 1, 0), min(cy + 2, ny)):
            for gx in range(max(cx - 1, 0), min(cx + 2, nx)):
                c = gy * nx + gx
                for m in range(cstart[c], cstart[c + 1]):
                    j = members[m]
                    if j <= i:
                        continue
                    dx = pos[i, 0] - pos[j, 0]
                    dy = pos[i, 1] - pos[j, 1]
                    cut = radius[i] + radius[j] + skin
                    if dx * dx + dy * dy < cut * cut:
                        if k == nbr.shape[0]:
                            nbr = _doubled(nbr, k)
                        # insertion keeps this disk's neighbours sorted
                        p = k
                        while p > first and nbr[p - 1] > j:
                            nbr[p] = nbr[p - 1]
                            p -= 1
                        nbr[p] = j
                        k += 1
        start[i + 1] = k
    nbr = nbr[:k].copy()
    ht = np.zeros(k)
    hr = np.zeros(k)
    hn = np.zeros(k)
    for i in range(n):
        io = new_to_old[i]
        if io < 0 or io + 1 >= old_start.shape[0]:
            continue
        q = old_start[io]
        q_end = old_start[io + 1]
        for p in range(start[i], start[i + 1]):
            jo = new_to_old[nbr[p]]
            if jo < 0:
                continue
            while q < q_end and old_nbr[q] < jo:
                q += 1
            if q < q_end and old_nbr[q] == jo:
                ht[p] = old_ht[q]
                hr[p] = old_hr[q]
                hn[p] = old_hn[q]
    return start, nbr, ht, hr, hn


@njit(inline="always", **HOT)
def _closest_on_segment(px, py, ax, ay, bx, by):
    ex = bx - ax
    ey = by - ay
    u = ((px - ax) * ex + (py - ay) * ey) / (ex * ex + ey * ey)
    u = min(max(u, 0.0), 1.0)
    return ax + u * ex, ay + u * ey


@njit(cache=True)
def build_wall_list(pos, radius, skin, walls, old_start, old_wall, old_ht, old_hr, old_hn,
                    new_to_old):
    """Disk-segment candidate list (CSR) within ``r_i + skin``, history carried over."""
    n = pos.shape[0]
    nw = walls.shape[0]
    start = np.zeros(n + 1, dtype=np.int64)
    wall = np.empty(n + 16, dtype=np.int64)
    k = 0
    for i in range(n):
        for w in range(nw):
            cx, cy = _closest_on_segment(pos[i, 0], pos[i, 1], walls[w, 0], walls[w, 1],
                                         walls[w, 2], walls[w, 3])
            dx = pos[i, 0] - cx
            dy = pos[i, 1] - cy
            cut = radius[i] + skin
            if dx * dx + dy * dy < cut * cut:
                if k == wall.shape[0]:
                    wall = _doubled(wall, k)
                wall[k] = w
                k += 1
        start[i + 1] = k
    wall = wall[:k].copy()
    ht = np.zeros(k)
    hr = np.zeros(k)
    hn = np.zeros(k)
    for i in range(n):
        io = new_to_old[i]
        if io < 0 or io + 1 >= old_start.shape[0]:
            continue
        for p in range(start[i], start[i + 1]):
            for q in range(old_start[io], old_start[io + 1]):
                if old_wall[q] == wall[p]:
                    ht[p] = old_ht[q]
                    hr[p] = old_hr[q]
                    hn[p] = old_hn[q]
    return start, wall, ht, hr, hn


@njit(inline="always", **HOT)
def _contact(kn, kt, cn, ct, mu, mur, kr_coef, coh, delta, vn, vt, wrel, m_eff, i_eff, r_eff,
             xi, theta, dt):
    """Normal force, tangential force, rolling torque and updated springs of one contact."""
    sq = math.sqrt(m_eff)
    fn = kn * delta - cn * sq * vn
    if fn < 0.0:
        fn = 0.0
    xi = xi + vt * dt
    ft = -kt * xi - ct * sq * vt
    limit = mu * fn
    if abs(ft) > limit:
        ft = limit if ft > 0.0 else -limit
        xi = -ft / kt
    mr = 0.0
    kr = kr_coef * r_eff * r_eff
    if kr > 0.0:
        theta = theta + wrel * dt
        # rolling dashpot with the normal damping ratio: cn / sqrt(kn) = 2 zeta
        mr = -kr * theta - cn * math.sqrt(kr * i_eff / kn) * wrel
        mlim = mur * r_eff * fn
        if abs(mr) > mlim:
            mr = mlim if mr > 0.0 else -mlim
            theta = -mr / kr
    else:
        theta = 0.0
    return fn - coh, ft, mr, xi, theta


@njit(parallel=True, **HOT)
def pair_pass(pos, vel, omega, radius, body_mass, inv_inertia, force, torque, start, nbr, ht, hr,
              wall_start, wall, wall_ht, wall_hr, walls, params, dt, pair_force, pair_torque):
    """Pass 1 of ``compute_forces``: pair forces stored per pair, each disk's
    own share (its pairs in list order, then its walls) summed into its row."""
    n = pos.shape[0]
    kn = params[P_KN]
    kt = params[P_KT]
    cn = params[P_CN]
    ct = params[P_CT]
    mu = params[P_MU]
    mur = params[P_MUR]
    krc = params[P_KR]
    coh = params[P_COH]
    for i in prange(n):
        xi_ = pos[i, 0]
        yi = pos[i, 1]
        ri = radius[i]
        mi = body_mass[i]
        fxi = 0.0
        fyi = 0.0
        ti = 0.0
        for p in range(start[i], start[i + 1]):
            j = nbr[p]
            dx = xi_ - pos[j, 0]
            dy = yi - pos[j, 1]
            rsum = ri + radius[j]
            d2 = dx * dx + dy * dy
            if d2 >= rsum * rsum:
                ht[p] = 0.0
                hr[p] = 0.0
                pair_force[p, 0] = 0.0
                pair_force[p, 1] = 0.0
                pair_torque[p] = 0.0
                continue
            d = math.sqrt(d2)
            nx_ = dx / d
            ny_ = dy / d
            dvx = vel[i, 0] - vel[j, 0]
            dvy = vel[i, 1] - vel[j, 1]
            rj = radius[j]
            vn = dvx * nx_ + dvy * ny_
            vt = -dvx * ny_ + dvy * nx_ - (ri * omega[i] + rj * omega[j])
            mj = body_mass[j]
            fn, ft, mr, xi, theta = _contact(kn, kt, cn, ct, mu, mur, krc, coh, rsum - d, vn, vt,
                                             omega[i] - omega[j], mi * mj / (mi + mj),
                                             1.0 / (inv_inertia[i] + inv_inertia[j]),
                                             ri * rj / rsum, ht[p], hr[p], dt)
            ht[p] = xi
            hr[p] = theta
            fx = fn * nx_ - ft * ny_
            fy = fn * ny_ + ft * nx_
            fxi += fx
            fyi += fy
            ti += -ri * ft + mr
            pair_force[p, 0] = fx
            pair_force[p, 1] = fy
            pair_torque[p] = -rj * ft - mr
        for p in range(wall_start[i], wall_start[i + 1]):
            w = wall[p]
            cx, cy = _closest_on_segment(xi_, yi, walls[w, 0], walls[w, 1], walls[w, 2], walls[w, 3])
            dx = xi_ - cx
            dy = yi - cy
            d2 = dx * dx + dy * dy
            if d2 >= ri * ri:
                wall_ht[p] = 0.0
                wall_hr[p] = 0.0
                continue
            d = math.sqrt(d2)
            nx_ = dx / d
            ny_ = dy / d
            vn = vel[i, 0] * nx_ + vel[i, 1] * ny_
            vt = -vel[i, 0] * ny_ + vel[i, 1] * nx_ - ri * omega[i]
            fn, ft, mr, xi, theta = _contact(kn, kt, cn, ct, mu, mur, krc, coh, ri - d, vn, vt,
                                             omega[i], mi, 1.0 / inv_inertia[i], ri,
                                             wall_ht[p], wall_hr[p], dt)
            wall_ht[p] = xi
            wall_hr[p] = theta
            fxi += fn * nx_ - ft * ny_
            fyi += fn * ny_ + ft * nx_
            ti += -ri * ft + mr
        force[i, 0] = fxi
        force[i, 1] = fyi
        torque[i] = ti


@njit(parallel=True, **HOT)
def compute_forces(pos, vel, omega, radius, body_mass, inv_inertia, force, torque, start, nbr, ht, hr,
                   wall_start, wall, wall_ht, wall_hr, walls, params, dt, pair_force, pair_torque,
                   rev_start, rev_pair):
    """Contact forces [N] and torques [N m] of all disks; updates contact history.

    Runs on all threads (``prange``) and gives the same bits for any thread
    count: each disk's sums are gathered in a fixed order. Pass 1
    (``pair_pass``: disk i owns the pairs ``start[i]:start[i+1]`` and its
    wall contacts): each pair's force on i and torque on j are stored per
    pair (``pair_force`` (P, 2), ``pair_torque`` (P,)) and i sums its own
    share in list order. Pass 2: disk j adds the opposite of the forces of
    the pairs it is the partner of, in increasing pair order (``rev_start``,
    ``rev_pair``: ``reverse_pairs``). ``run_steps`` fuses pass 2 with the
    integration (``gather_and_integrate``): one join fewer per step.
    """
    pair_pass(pos, vel, omega, radius, body_mass, inv_inertia, force, torque, start, nbr, ht, hr,
              wall_start, wall, wall_ht, wall_hr, walls, params, dt, pair_force, pair_torque)
    for j in prange(pos.shape[0]):
        fxj, fyj, tj = _gathered(j, pair_force, pair_torque, rev_start, rev_pair)
        force[j, 0] += fxj
        force[j, 1] += fyj
        torque[j] += tj


@njit(inline="always", **HOT)
def _gathered(j, pair_force, pair_torque, rev_start, rev_pair):
    fxj = 0.0
    fyj = 0.0
    tj = 0.0
    for q in range(rev_start[j], rev_start[j + 1]):
        p = rev_pair[q]
        fxj -= pair_force[p, 0]
        fyj -= pair_force[p, 1]
        tj += pair_torque[p]
    return fxj, fyj, tj


@njit(parallel=True, **HOT)
def gather_and_integrate(dt, g, pos, vel, omega, force, torque, inv_mass, inv_inertia, ref_pos,
                         limit2, pair_force, pair_torque, rev_start, rev_pair):
    """Pass 2 of ``compute_forces`` and the symplectic Euler step of each disk
    in one loop on all threads; returns how many disks moved more than
    ``sqrt(limit2)`` [m] since the list build (an integer sum: any thread count)."""
    moved = 0
    for i in prange(pos.shape[0]):
        fxj, fyj, tj = _gathered(i, pair_force, pair_torque, rev_start, rev_pair)
        fx = force[i, 0] + fxj
        fy = force[i, 1] + fyj
        t = torque[i] + tj
        force[i, 0] = fx
        force[i, 1] = fy
        torque[i] = t
        vel[i, 0] += fx * inv_mass[i] * dt
        vel[i, 1] += (fy * inv_mass[i] - g) * dt
        omega[i] += t * inv_inertia[i] * dt
        pos[i, 0] += vel[i, 0] * dt
        pos[i, 1] += vel[i, 1] * dt
        dx = pos[i, 0] - ref_pos[i, 0]
        dy = pos[i, 1] - ref_pos[i, 1]
        if dx * dx + dy * dy > limit2:
            moved += 1
    return moved


@njit(cache=True)
def reverse_pairs(start, nbr):
    """For each disk j the pairs ``p`` with ``nbr[p] == j``, in increasing p
    (CSR ``rev_start`` (N+1,), ``rev_pair`` (P,)): the partner side of the
    half list, for the gather of ``compute_forces``."""
    n = start.shape[0] - 1
    rev_start = np.zeros(n + 1, np.int64)
    for p in range(nbr.shape[0]):
        rev_start[nbr[p] + 1] += 1
    for j in range(n):
        rev_start[j + 1] += rev_start[j]
    fill = rev_start[:-1].copy()
    rev_pair = np.empty(nbr.shape[0], np.int64)
    for p in range(nbr.shape[0]):
        j = nbr[p]
        rev_pair[fill[j]] = p
        fill[j] += 1
    return rev_start, rev_pair


@njit(**HOT)
def run_steps(n_steps, dt, time, pos, vel, omega, force, torque, radius, body_mass, inv_mass,
              inv_inertia, start, nbr, ht, hr, wall_start, wall, wall_ht, wall_hr, walls, params,
              ref_pos, half_skin, candidates, outlet_lo, outlet_hi, zone_top, rates, credits,
              credit_cap, tracked_mass, removed, speed_limit, box, pair_force, pair_torque,
              rev_start, rev_pair):
    """Advance up to ``n_steps`` steps of ``dt`` [s] from ``time`` [s].

    Stops early after a step in which a disk moved more than ``half_skin``
    since the last list build (the caller rebuilds) or the feeder of an
    outlet took disks (their rows are written to ``removed``; the caller
    removes them). Feeder rule: each outlet accumulates a mass credit
    ``rate dt`` per step and takes the lowest disk whose centre lies in its
    zone (``outlet_lo <= x <= outlet_hi``, ``y <= zone_top``) whenever the
    credit covers that disk's tracked mass; with no disk in the zone the
    credit is capped at ``credit_cap`` [kg] so an empty feeder does not
    store up a burst.

    Blow-up guard: also stops after a step that left a disk faster than
    ``speed_limit`` [m/s] (or with a non-finite velocity) or outside the
    container ``box = (x_min, x_max, y_min)`` [m]; its row is returned.

    Returns ``(steps_done, time, n_removed, rebuild_needed, bad_row, bad_kind)``
    with ``bad_kind`` one of ``GUARD_NONE``, ``GUARD_SPEED``, ``GUARD_OUTSIDE``.
    """
    g = params[P_G]
    limit2 = half_skin * half_skin
    speed2 = speed_limit * speed_limit
    n_removed = 0
    for step in range(n_steps):
        pair_pass(pos, vel, omega, radius, body_mass, inv_inertia, force, torque, start, nbr, ht,
                  hr, wall_start, wall, wall_ht, wall_hr, walls, params, dt, pair_force,
                  pair_torque)
        moved = gather_and_integrate(dt, g, pos, vel, omega, force, torque, inv_mass,
                                     inv_inertia, ref_pos, limit2, pair_force, pair_torque,
                                     rev_start, rev_pair) > 0
        time += dt
        bad_row, bad_kind = guard_scan(pos, vel, speed2, box)
        if bad_kind != GUARD_NONE:
            return step + 1, time, n_removed, moved, bad_row, bad_kind
        n_removed = feed(dt, pos, candidates, outlet_lo, outlet_hi, zone_top, rates, credits,
                         credit_cap, tracked_mass, removed, n_removed)
        if n_removed > 0 or moved:
            return step + 1, time, n_removed, moved, -1, GUARD_NONE
    return n_steps, time, n_removed, False, -1, GUARD_NONE


PARALLEL_MIN_DISKS = 4000
"""Fewest disks for which ``Dem.step`` runs the kernels on all threads; below
it on one (``numba.set_num_threads(1)``): a step is then too short for the
threads' start and join to pay, and on a busy machine a descheduled thread
stalls every step. The bits are the same either way."""


@njit(**HOT)
def feed(dt, pos, candidates, outlet_lo, outlet_hi, zone_top, rates, credits, credit_cap,
         tracked_mass, removed, n_removed):
    """One step of the feeders (rule in ``run_steps``); returns the rows removed so far."""
    for o in range(rates.shape[0]):
        if rates[o] <= 0.0:
            continue
        credits[o] += rates[o] * dt
        while True:
            best = -1
            for c in range(candidates.shape[0]):
                i = candidates[c]
                if i < 0:
                    continue
                if outlet_lo[o] <= pos[i, 0] <= outlet_hi[o] and pos[i, 1] <= zone_top:
                    if best < 0 or pos[i, 1] < pos[best, 1]:
                        best = i
            if best < 0:
                credits[o] = min(credits[o], credit_cap)
                break
            if credits[o] < tracked_mass[best] or n_removed == removed.shape[0]:
                break
            credits[o] -= tracked_mass[best]
            removed[n_removed] = best
            n_removed += 1
            for c in range(candidates.shape[0]):
                if candidates[c] == best:
                    candidates[c] = -1
    return n_removed


GUARD_NONE, GUARD_SPEED, GUARD_OUTSIDE = 0, 1, 2
"""Codes of what the per-step blow-up guard saw (``run_steps``)."""


@njit(cache=True, parallel=True, error_model="numpy")  # no fastmath: it may assume NaN away
def _guard_count(pos, vel, speed2, box):
    bad = 0
    for i in prange(pos.shape[0]):
        s2 = vel[i, 0] * vel[i, 0] + vel[i, 1] * vel[i, 1]
        x = pos[i, 0]
        # written so that NaN fails the tests
        if not (s2 <= speed2 and box[0] <= x <= box[1] and pos[i, 1] >= box[2]):
            bad += 1
    return bad


@njit(cache=True, error_model="numpy")
def guard_scan(pos, vel, speed2, box):
    """First row faster than ``sqrt(speed2)`` [m/s] (or non-finite) or outside
    ``box = (x_min, x_max, y_min)`` [m], and what it was (``GUARD_*``); the
    count runs on all threads, the search only after a failure."""
    if _guard_count(pos, vel, speed2, box) == 0:
        return -1, GUARD_NONE
    for i in range(pos.shape[0]):
        s2 = vel[i, 0] * vel[i, 0] + vel[i, 1] * vel[i, 1]
        # written so that NaN fails the test
        if not s2 <= speed2:
            return i, GUARD_SPEED
        x = pos[i, 0]
        if not (box[0] <= x <= box[1] and pos[i, 1] >= box[2]):
            return i, GUARD_OUTSIDE
    return -1, GUARD_NONE


@njit(cache=True)
def zone_candidates(pos, outlet_lo, outlet_hi, zone_top, margin):
    """Rows of disks within ``margin`` [m] of any feeder zone (valid until next rebuild)."""
    n = pos.shape[0]
    out = np.empty(n, dtype=np.int64)
    k = 0
    for i in range(n):
        if pos[i, 1] > zone_top + margin:
            continue
        for o in range(outlet_lo.shape[0]):
            if outlet_lo[o] - margin <= pos[i, 0] <= outlet_hi[o] + margin:
                out[k] = i
                k += 1
                break
    return out[:k].copy()


@njit(cache=True)
def elastic_energy(pos, radius, start, nbr, wall_start, wall, walls, ht, wall_ht, params):
    """Energy [J] stored in the normal and tangential springs."""
    kn = params[P_KN]
    kt = params[P_KT]
    e = 0.0
    for i in range(pos.shape[0]):
        for p in range(start[i], start[i + 1]):
            j = nbr[p]
            dx = pos[i, 0] - pos[j, 0]
            dy = pos[i, 1] - pos[j, 1]
            delta = radius[i] + radius[j] - math.sqrt(dx * dx + dy * dy)
            if delta > 0.0:
                e += 0.5 * kn * delta * delta + 0.5 * kt * ht[p] * ht[p]
        for p in range(wall_start[i], wall_start[i + 1]):
            w = wall[p]
            cx, cy = _closest_on_segment(pos[i, 0], pos[i, 1], walls[w, 0], walls[w, 1],
                                         walls[w, 2], walls[w, 3])
            dx = pos[i, 0] - cx
            dy = pos[i, 1] - cy
            delta = radius[i] - math.sqrt(dx * dx + dy * dy)
            if delta > 0.0:
                e += 0.5 * kn * delta * delta + 0.5 * kt * wall_ht[p] * wall_ht[p]
    return e


@njit(cache=True)
def max_overlap_ratio(pos, radius, start, nbr):
    """Largest pair overlap divided by the smaller diameter [-]."""
    worst = 0.0
    for i in range(pos.shape[0]):
        for p in range(start[i], start[i + 1]):
            j = nbr[p]
            dx = pos[i, 0] - pos[j, 0]
            dy = pos[i, 1] - pos[j, 1]
            delta = radius[i] + radius[j] - math.sqrt(dx * dx + dy * dy)
            ratio = delta / (2.0 * min(radius[i], radius[j]))
            if ratio > worst:
                worst = ratio
    return worst
