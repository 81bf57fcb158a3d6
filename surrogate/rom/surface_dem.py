"""Surface layer by resolved DEM: incoming particles fall, impact and spread.

Source: paper section "Digital twin as a distributed particle simulation"
("To accurately capture the dispersion of particles impacting the pile
surfaces, resolved DEM is used") and section "Integration test" ("The
particles fall, impact, and disperse over the pile surface as simulated by
the physics-based stockpile model"); Wallin and Servin (2021) couple the
ROM bulk to DEM for the free particles in the same way.

Model:

- Free particles are 2D DEM disks with the training DEM's contact law
  (``surrogate.dem.kernels._contact``: linear spring-dashpot, tangential
  spring with Coulomb limit, rolling resistance), its particle density and
  size clipping (``DemConfig.diameter_of_mass``) and its inlet height and
  velocity; they are released across the inlet width (``add``).
- Above the pile they touch nothing (the inlet releases them a row apart
  at one speed), so they fly ballistically, computed in closed form, until
  they are two particle radii above the bed (``_fall``): for a particle
  still falling straight down from the inlet, above the bed under the
  inlet's stream (a column of the bulk piled high beside it is not in its
  way); for one that has hit something, above the whole bed.
- The bulk is the bed they land on: fixed disks (infinite mass, at rest)
  laid along the bulk's surface profile for one call of ``advance``
  (``SurfaceDem.boundary``); the floor and the container's side walls are
  walls. Free particles collide with the bed, the walls and each other.
- Integration: symplectic Euler as in ``surrogate.dem.kernels.run_steps``,
  ``v += (F/m - g) dt; x += v dt; w += (M/I) dt``, at the DEM's own step
  t_c / ``dt_safety_factor`` (t_c the DEM's contact time; a call of
  ``advance`` takes the largest step that divides it and is not above).
- The impact: ``impact_time`` seconds after its first contact a particle
  joins the bulk where it is (the storage then lets it roll down the
  surface by the angle-of-repose rule, ``surrogate.rom.surface.deposit``).
  Why not longer: a fixed bed does not give way as a loose one does, so a
  particle kept in the DEM on it hops and rolls far down the flanks. On a
  settled 30 t pile of the training DEM fed at 200 kg/s, pooled over four
  piles and feeds, the DEM's newcomers rest (4 s after entry) a median
  1.0 m from the inlet; the surface layer puts them 0.55 m further out
  (sd 0.20 m over seed subsets), and kept in the fixed-bed DEM for 2 s they
  end 3.96 m further out (sd 0.65 m) (``tests/test_rom_surface.py``, slow).
- Contact history (tangential and rolling springs) is kept in
  ``HISTORY_SLOTS`` slots per particle for the length of one ``advance``
  call (the bed is rebuilt between calls).

Parameters (``SurfaceDem``)
----------
config : DemConfig
    The DEM whose contact law, sizes, density and inlet (``inlets[0]``; its
    x replaced by the container's ``inlet_x``) are used.
container : Container
    Floor and side walls [m].
dt_safety_factor : float, optional
    Time step = contact time / this (default the DEM's ``dt_safety_factor``;
    at least 5, the DEM's minimum).
impact_time : float
    Seconds from the first contact to joining the bulk (default 0.05 s,
    about ten contact times of the training DEM).
rng : numpy.random.Generator, optional
    Draws the release positions across the inlet (default seed 0).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from cosim.errors import ValidationError, check_finite_range
from surrogate.dem import kernels
from surrogate.dem.config import GRAVITY, DemConfig
from surrogate.dem.emitter import inlet_positions
from surrogate.rom.container import Container
from surrogate.rom.surface import surface_heights

HISTORY_SLOTS = 8
"""Contacts per free particle whose springs are remembered."""


@njit(inline="always", **kernels.HOT)
def _slot(partner, i, code):
    """Slot of contact ``code`` of particle i, a new one (zeroed) or -1 if all are taken."""
    empty = -1
    for s in range(partner.shape[1]):
        if partner[i, s] == code:
            return s
        if empty < 0 and partner[i, s] < 0:
            empty = s
    if empty >= 0:
        partner[i, empty] = code
    return empty


@njit(inline="always", **kernels.HOT)
def _touch(params, partner, hist_t, hist_r, seen, i, code, delta, nx_, ny_, vn, vt, wrel, m_eff,
           i_eff, r_eff, dt):
    """One contact of particle i: force (x, y) and torques on i; springs kept in i's slot."""
    s = _slot(partner, i, code)
    xi = hist_t[i, s] if s >= 0 else 0.0
    theta = hist_r[i, s] if s >= 0 else 0.0
    if s >= 0:
        seen[s] = True
    fn, ft, mr, xi, theta = kernels._contact(
        params[kernels.P_KN], params[kernels.P_KT], params[kernels.P_CN], params[kernels.P_CT],
        params[kernels.P_MU], params[kernels.P_MUR], params[kernels.P_KR], params[kernels.P_COH],
        delta, vn, vt, wrel, m_eff, i_eff, r_eff, xi, theta, dt)
    if s >= 0:
        hist_t[i, s] = xi
        hist_r[i, s] = theta
    return fn * nx_ - ft * ny_, fn * ny_ + ft * nx_, ft, mr


@njit(**kernels.HOT)
def _advance(n_steps, dt, pos, vel, omega, radius, body_mass, inv_inertia, active, first_step,
             arrival_order, impact_age, fixed_pos, fixed_radius, cell_start, cell_members,
             grid_x0, grid_y0, cell_size, grid_nx, grid_ny, partner, hist_t, hist_r, x_min, x_max,
             floor, params, impact_time):
    """``n_steps`` steps of ``dt``; particle i takes part from step ``first_step[i]``
    (``arrival_order`` sorts them by it) until it joins the bulk (``active[i]``
    becomes False). Only the particles taking part are visited, and steps in
    which none does are skipped."""
    n = pos.shape[0]
    n_fixed = fixed_pos.shape[0]
    g = params[kernels.P_G]
    r_max = radius.max()
    force = np.zeros((n, 2))
    torque = np.zeros(n)
    touching = np.zeros(n, np.bool_)
    seen = np.zeros(partner.shape[1], np.bool_)
    zone = np.empty(n, np.int64)  # the particles taking part, in arrival order
    in_zone = 0
    arrived = 0
    step = 0
    while step < n_steps:
        while arrived < n and first_step[arrival_order[arrived]] <= step:
            zone[in_zone] = arrival_order[arrived]
            in_zone += 1
            arrived += 1
        if in_zone == 0:
            if arrived == n or first_step[arrival_order[arrived]] >= n_steps:
                return
            step = first_step[arrival_order[arrived]]
            continue
        for z in range(in_zone):
            i = zone[z]
            force[i, 0] = 0.0
            force[i, 1] = 0.0
            torque[i] = 0.0
            touching[i] = False
        for z in range(in_zone):
            i = zone[z]
            seen[:] = False
            xi_, yi, ri, mi = pos[i, 0], pos[i, 1], radius[i], body_mass[i]
            # fixed boundary disks in the 3 x 3 cells around i
            cx = int(math.floor((xi_ - grid_x0) / cell_size))
            cy = int(math.floor((yi - grid_y0) / cell_size))
            for ky in range(max(cy - 1, 0), min(cy + 2, grid_ny)):
                for kx in range(max(cx - 1, 0), min(cx + 2, grid_nx)):
                    c = ky * grid_nx + kx
                    for m in range(cell_start[c], cell_start[c + 1]):
                        j = cell_members[m]
                        dx = xi_ - fixed_pos[j, 0]
                        dy = yi - fixed_pos[j, 1]
                        rsum = ri + fixed_radius[j]
                        d2 = dx * dx + dy * dy
                        if d2 >= rsum * rsum:
                            continue
                        d = math.sqrt(d2)
                        nx_, ny_ = dx / d, dy / d
                        vn = vel[i, 0] * nx_ + vel[i, 1] * ny_
                        vt = -vel[i, 0] * ny_ + vel[i, 1] * nx_ - ri * omega[i]
                        r_eff = ri * fixed_radius[j] / rsum
                        fx, fy, ft, mr = _touch(params, partner, hist_t, hist_r, seen, i, j,
                                                rsum - d, nx_, ny_, vn, vt, omega[i], mi,
                                                1.0 / inv_inertia[i], r_eff, dt)
                        force[i, 0] += fx
                        force[i, 1] += fy
                        torque[i] += -ri * ft + mr
                        touching[i] = True
            # the other free particles taking part (few: all pairs)
            for y in range(z + 1, in_zone):
                j = zone[y]
                dy = yi - pos[j, 1]
                if abs(dy) >= ri + r_max:
                    continue
                dx = xi_ - pos[j, 0]
                rj = radius[j]
                rsum = ri + rj
                d2 = dx * dx + dy * dy
                if d2 >= rsum * rsum:
                    continue
                d = math.sqrt(d2)
                nx_, ny_ = dx / d, dy / d
                dvx = vel[i, 0] - vel[j, 0]
                dvy = vel[i, 1] - vel[j, 1]
                vn = dvx * nx_ + dvy * ny_
                vt = -dvx * ny_ + dvy * nx_ - (ri * omega[i] + rj * omega[j])
                mj = body_mass[j]
                fx, fy, ft, mr = _touch(params, partner, hist_t, hist_r, seen, i, n_fixed + j,
                                        rsum - d, nx_, ny_, vn, vt, omega[i] - omega[j],
                                        mi * mj / (mi + mj),
                                        1.0 / (inv_inertia[i] + inv_inertia[j]), ri * rj / rsum,
                                        dt)
                force[i, 0] += fx
                force[i, 1] += fy
                torque[i] += -ri * ft + mr
                force[j, 0] -= fx
                force[j, 1] -= fy
                torque[j] += -rj * ft - mr
                touching[i] = True
                touching[j] = True
            # floor and side walls (codes after all disks)
            for w in range(3):
                if w == 0:
                    gap, nx_, ny_ = yi - floor, 0.0, 1.0
                elif w == 1:
                    gap, nx_, ny_ = xi_ - x_min, 1.0, 0.0
                else:
                    gap, nx_, ny_ = x_max - xi_, -1.0, 0.0
                code = n_fixed + n + w
                if gap >= ri:
                    continue
                vn = vel[i, 0] * nx_ + vel[i, 1] * ny_
                vt = -vel[i, 0] * ny_ + vel[i, 1] * nx_ - ri * omega[i]
                fx, fy, ft, mr = _touch(params, partner, hist_t, hist_r, seen, i, code, ri - gap,
                                        nx_, ny_, vn, vt, omega[i], mi, 1.0 / inv_inertia[i], ri,
                                        dt)
                force[i, 0] += fx
                force[i, 1] += fy
                torque[i] += -ri * ft + mr
                touching[i] = True
            # contacts that ended free their slots
            for s in range(partner.shape[1]):
                if partner[i, s] >= 0 and not seen[s]:
                    partner[i, s] = -1
                    hist_t[i, s] = 0.0
                    hist_r[i, s] = 0.0
        kept = 0
        for z in range(in_zone):
            i = zone[z]
            vel[i, 0] += force[i, 0] / body_mass[i] * dt
            vel[i, 1] += (force[i, 1] / body_mass[i] - g) * dt
            omega[i] += torque[i] * inv_inertia[i] * dt
            pos[i, 0] += vel[i, 0] * dt
            pos[i, 1] += vel[i, 1] * dt
            # the impact window runs from the first contact, touching or not
            if touching[i] or impact_age[i] > 0.0:
                impact_age[i] += dt
                if impact_age[i] >= impact_time:
                    active[i] = False
            if active[i]:
                zone[kept] = i
                kept += 1
        in_zone = kept
        step += 1


def _median_diameter(config, mass: np.ndarray) -> float:
    """The median of ``config.diameter_of_mass(mass)`` [m], converting only the middle
    masses: the diameter grows with the mass, so it has the same order."""
    n = mass.size
    middle = [(n - 1) // 2, n // 2]
    return float(np.median(config.diameter_of_mass(np.partition(mass, middle)[middle])))


class SurfaceDem:
    """Free particles between the inlet and the bulk (see the module docstring)."""

    def __init__(self, config: DemConfig, container: Container,
                 dt_safety_factor: float | None = None, impact_time: float = 0.05,
                 rng: np.random.Generator | None = None):
        if dt_safety_factor is None:
            dt_safety_factor = config.dt_safety_factor
        if not float(dt_safety_factor) >= 5.0:
            raise ValidationError("surface_dt_safety_factor", ">= 5 (the DEM's minimum)",
                                  f"got {dt_safety_factor!r}")
        self.impact_time = float(check_finite_range("impact_time", impact_time, 0.0,
                                                    low_open=True, unit="s"))
        inlet_height = float(config.inlets[0][1])
        self.config = DemConfig.from_dict({**config.to_dict(),
                                           "inlets": [[container.inlet_x, inlet_height]]})
        self.container = container
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.dt = self.config.contact_time / float(dt_safety_factor)
        self.params = kernels.contact_params(self.config, GRAVITY)
        self.ids = np.empty(0, np.uint64)
        self.mass = np.empty(0)
        self.radius = np.empty(0)
        self.pos = np.empty((0, 2))
        self.vel = np.empty((0, 2))
        self.omega = np.empty(0)
        self.impact_age = np.empty(0)

    def __len__(self) -> int:
        return int(self.ids.size)

    def add(self, ids, mass) -> np.ndarray:
        """Release particles ``ids`` of ``mass`` [kg] at the inlet; return their positions."""
        mass = np.asarray(mass, dtype=np.float64)
        radius = 0.5 * self.config.diameter_of_mass(mass)
        position = inlet_positions(self.config, 0, radius, self.pos, self.radius)
        # the falling stream's spread: anywhere across the inlet, not in the emitter's lanes
        half = 0.5 * self.config.inlet_width
        position[:, 0] = self.container.inlet_x + self.rng.uniform(-half, half, mass.size)
        velocity = np.zeros((mass.size, 2))
        velocity[:, 1] = -self.config.inlet_velocity
        self.ids = np.concatenate((self.ids, np.asarray(ids, dtype=np.uint64)))
        self.mass = np.concatenate((self.mass, mass))
        self.radius = np.concatenate((self.radius, radius))
        self.pos = np.concatenate((self.pos, position))
        self.vel = np.concatenate((self.vel, velocity))
        self.omega = np.concatenate((self.omega, np.zeros(mass.size)))
        self.impact_age = np.concatenate((self.impact_age, np.zeros(mass.size)))
        return position

    def boundary(self, column_width: float, bulk_pos: np.ndarray, bulk_mass: np.ndarray,
                 heights: np.ndarray | None = None):
        """The bulk as the free particles see it: ``(position, radius)`` of the fixed
        bed disks (``heights``: the bulk's ``surface_heights`` at ``column_width``,
        if the caller has them already).

        The surface is the bulk's height profile over its packing columns
        (``surrogate.rom.surface.surface_heights``, the same packing the bulk
        is kept in); the bed is one layer of disks of the bulk's median size
        R laid along it (their tops on the surface), so a landing particle
        meets the pockets of a granular bed, not a smooth slope. Their spacing
        4 R sin(phi), with phi the DEM's angle of repose
        (``Container.repose_angle``), makes the pockets just deep enough that
        a particle of size R rests in one on a slope below phi and rolls on
        over a steeper one (it must lift its centre over the downhill bed
        disk: it rolls out once the slope exceeds asin(spacing / 4 R)).
        """
        c = self.container
        if heights is None:
            heights = surface_heights(c, column_width, bulk_pos, bulk_mass)
        if bulk_pos.shape[0] == 0:
            return np.empty((0, 2)), np.empty(0)
        radius = 0.5 * _median_diameter(self.config, bulk_mass)
        centres = c.x_min + (np.arange(heights.size) + 0.5) * (c.x_max - c.x_min) / heights.size
        x = np.concatenate(([c.x_min], centres, [c.x_max]))
        y = np.concatenate((heights[:1], heights, heights[-1:]))
        arc = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))))
        spacing = 4.0 * radius * np.sin(c.repose_angle)
        along = np.arange(0.5 * spacing, arc[-1], spacing)
        bed = np.column_stack((np.interp(along, arc, x), np.interp(along, arc, y) - radius))
        return bed, np.full(along.size, radius)

    def _entry_heights(self, fixed_pos: np.ndarray, fixed_radius: np.ndarray) -> np.ndarray:
        """Per particle, the height [m] above which it touches nothing: two largest
        radii over the top of the bed disks it can reach. For a particle still
        falling straight down from the inlet (no sideways speed, no contact yet)
        those are the disks within its reach across the inlet's width; for any
        other, the whole bed."""
        r_max = 0.5 * self.config.diameter_max
        if fixed_radius.size == 0:
            return np.full(self.ids.size, self.container.floor + 2.0 * r_max)
        top = fixed_pos[:, 1] + fixed_radius
        reach = 0.5 * self.config.inlet_width + r_max + fixed_radius
        under_stream = np.abs(fixed_pos[:, 0] - self.container.inlet_x) <= reach
        stream_top = top[under_stream].max() if under_stream.any() else self.container.floor
        falling = (self.vel[:, 0] == 0.0) & (self.impact_age == 0.0)
        return np.where(falling, stream_top, top.max()) + 2.0 * r_max

    def _fall(self, dt: float, steps: int, entry_height: np.ndarray) -> np.ndarray:
        """Move the particles above their ``entry_height`` [m] ballistically (they
        touch nothing up there: the inlet releases them a row apart at one speed)
        up to the step at which they reach it; returns that step per particle
        (``steps`` if they stay above it for the whole call)."""
        g = GRAVITY
        height = self.pos[:, 1] - entry_height
        up = self.vel[:, 1]
        above = height > 0
        arrival = np.where(above, (up + np.sqrt(up * up + 2.0 * g * np.maximum(height, 0.0))) / g,
                           0.0)
        first = np.minimum(np.floor(arrival / dt), steps).astype(np.int64)
        flight = np.where(above, first * dt, 0.0)
        self.pos[:, 0] += self.vel[:, 0] * flight
        self.pos[:, 1] += up * flight - 0.5 * g * flight ** 2
        self.vel[:, 1] -= g * flight
        c = self.container
        np.clip(self.pos[:, 0], c.x_min + self.radius, c.x_max - self.radius, out=self.pos[:, 0])
        return first

    def advance(self, seconds: float, column_width: float, bulk_pos: np.ndarray,
                bulk_mass: np.ndarray, heights: np.ndarray | None = None):
        """Run the free particles ``seconds`` [s] over the bulk at rest (``heights``:
        as for ``boundary``).

        Returns ``(ids, mass, position)`` of the particles that joined the
        bulk (removed from the surface layer), in their order of arrival.
        """
        empty = (np.empty(0, np.uint64), np.empty(0), np.empty((0, 2)))
        if self.ids.size == 0 or seconds <= 0:
            return empty
        fixed_pos, fixed_radius = self.boundary(column_width, bulk_pos, bulk_mass, heights)
        r_max = 0.5 * self.config.diameter_max
        steps = int(np.ceil(seconds / self.dt - 1e-9))
        dt = seconds / steps
        first = self._fall(dt, steps, self._entry_heights(fixed_pos, fixed_radius))
        if fixed_pos.shape[0]:  # the DEM's cell sort; it may widen the cells, never narrow them
            x0, y0, cell, nx, ny, start, members = kernels._cell_grid(fixed_pos, 4.0 * r_max)
        else:
            x0, y0, cell, nx, ny = 0.0, 0.0, 4.0 * r_max, 1, 1
            start, members = np.zeros(2, np.int64), np.zeros(0, np.int64)
        n = self.ids.size
        body = self.config.sphere_mass(2.0 * self.radius)
        active = np.ones(n, dtype=np.bool_)
        c = self.container
        _advance(steps, dt, self.pos, self.vel, self.omega, self.radius, body,
                 1.0 / (0.4 * body * self.radius ** 2), active, first,
                 np.argsort(first, kind="stable"), self.impact_age,
                 fixed_pos, np.ascontiguousarray(fixed_radius), start, members, x0, y0,
                 cell, nx, ny, np.full((n, HISTORY_SLOTS), -1, np.int64),
                 np.zeros((n, HISTORY_SLOTS)), np.zeros((n, HISTORY_SLOTS)), c.x_min, c.x_max,
                 c.floor, self.params, self.impact_time)
        joined = ~active
        if not joined.any():
            return empty
        out = (self.ids[joined], self.mass[joined], self.pos[joined].copy())
        self._keep(active)
        return out

    def _keep(self, keep: np.ndarray) -> None:
        for name in ("ids", "mass", "radius", "pos", "vel", "omega", "impact_age"):
            setattr(self, name, getattr(self, name)[keep])

    def remove(self, ids) -> None:
        """Forget particles ``ids`` (they left the storage by other means)."""
        self._keep(~np.isin(self.ids, ids))
