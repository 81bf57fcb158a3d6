"""The 2D stockpile DEM: state, emission, feeder discharge, stepping, checkpoints.

Source: paper section "Digital twin as a distributed particle simulation"
(DEM with pseudo-particles calibrated to bulk density, friction, cohesion and
angle of repose; particles fall, impact and spread over the pile; particles
at the outlet are removed and reported) and section "Integration test". The
contact law and time-step rule are in ``kernels.py`` / ``config.py`` and in
``README.md`` next to this file.
"""

from __future__ import annotations

import json
import math
import warnings

import numba
import numpy as np

from cosim.errors import ValidationError, check_finite_range
from cosim.sizes import N_CLASSES, check_fractions
from surrogate.dem import emitter, kernels, nonsmooth
from surrogate.dem.config import GRAVITY, DemConfig
from surrogate.dem.geometry import feeder_zones, wall_segments

_PARTICLE_FIELDS = ("pos", "vel", "omega", "radius", "body_mass", "inv_mass", "inv_inertia",
                    "id", "tracking_id", "mass", "grade", "hardness", "f", "entry_time")
_LIST_FIELDS = ("start", "nbr", "ht", "hr", "hn", "wall_start", "wall", "wall_ht", "wall_hr",
                "wall_hn", "ref_pos", "candidates")
_RECORD_FIELDS = ("id", "tracking_id", "mass", "grade", "hardness", "f", "entry_time", "time",
                  "outlet")


GUARD_INTERVAL = 0.01
"""Simulated time [s] between the energy and overlap checks of the blow-up
guard (speeds and positions are checked every step)."""


_CHECK_NOW = 2 ** 62
"""Steps-since-check value that makes the guard check after the next step."""


class FeederCapped(UserWarning):
    """A feeder setpoint above what its opening passes was capped (``Dem.set_discharge_rate``)."""


class DemBlowUp(RuntimeError):
    """The DEM blew up (``DemConfig``, "Blow-up guard"): a disk too fast or
    outside the container, energy gained, or overlaps no contact law allows.

    Attributes: ``kind`` ("speed", "outside", "energy", "overlap"), ``seen``
    (what was measured, in words), ``time`` [s], ``step`` (steps done) and
    ``cause`` (why, as far as the DEM can tell). The DEM keeps its state at
    the failure (for pictures) and refuses to step on.
    """

    def __init__(self, kind: str, seen: str, time: float, step: int, cause: str):
        self.kind, self.seen, self.time, self.step, self.cause = kind, seen, time, step, cause
        super().__init__(f"DEM blew up at t = {time:.6g} s (step {step}): {seen}; {cause}")


def _empty_records() -> dict:
    return {"id": np.empty(0, np.uint64), "tracking_id": np.empty(0, np.uint64),
            "mass": np.empty(0), "grade": np.empty(0), "hardness": np.empty(0),
            "f": np.empty((0, N_CLASSES)), "entry_time": np.empty(0), "time": np.empty(0),
            "outlet": np.empty(0, np.int64)}


class Dem:
    """2D soft-disk DEM of a stockpile with inlets and feeder outlets.

    Parameters
    ----------
    cfg : DemConfig
        Geometry, material and time-step rule (SI units).
    seed : int
        Seed of the generator that splits emitted lots into particles.
    dt : float, optional
        Time step [s]; default ``cfg.stable_dt``. A larger step is refused
        unless ``force=True`` (stability studies only).
    force : bool
        Accept a ``dt`` above the stability limit.
    """

    def __init__(self, cfg: DemConfig | None = None, seed: int = 0, dt: float | None = None,
                 force: bool = False):
        self.cfg = cfg if cfg is not None else DemConfig()
        self.rng = np.random.default_rng(seed)
        self.walls = wall_segments(self.cfg)
        self._zone_lo, self._zone_hi, self._zone_top = feeder_zones(self.cfg)
        self.params = kernels.contact_params(self.cfg, GRAVITY)
        self.time = 0.0
        self.steps_done = 0
        self.nonsmooth = self.cfg.method == "nonsmooth"
        self.solver = nonsmooth.solver_params(self.cfg)
        self.solver_stats = np.zeros(nonsmooth.N_STATS)
        """Nonsmooth solver totals: steps, sweeps, contact rows, last sweep's
        largest velocity change [m/s], re-solves for missed contacts, unconverged
        steps, sum of the steps' last-sweep changes [m/s] (``nonsmooth.run_steps``)."""
        self._skin = self.cfg.skin
        self.threads = self.cfg.threads
        """Threads of the explicit kernels (``DemConfig.threads``); may be changed."""
        self.dt = self.cfg.nonsmooth_dt if self.nonsmooth else self.cfg.stable_dt
        if dt is not None:
            self.set_dt(dt, force=force)
        n_out = len(self.cfg.outlets)
        self.rates = np.zeros(n_out)
        self.setpoints = np.zeros(n_out)
        self.credits = np.zeros(n_out)
        self.credit_cap = float(self.cfg.sphere_mass(self.cfg.diameter_max))
        self.next_id = 0
        self.emitted_mass = 0.0
        self.discharged_mass = 0.0
        self._records = [_empty_records()]
        self.list_builds = 0
        walls = self.walls
        margin = self.cfg.diameter_max
        self._box = np.array([min(walls[:, 0].min(), walls[:, 2].min()) - margin,
                              max(walls[:, 0].max(), walls[:, 2].max()) + margin,
                              min(walls[:, 1].min(), walls[:, 3].min()) - margin])
        self._entry_top = max(float(y) for _, y in self.cfg.inlets)
        self._energy_budget = None
        self._steps_since_check = 0
        self.failure = None
        self._init_arrays()

    # ------------------------------------------------------------ state
    def _init_arrays(self):
        self.pos = np.zeros((0, 2))
        self.vel = np.zeros((0, 2))
        self.omega = np.zeros(0)
        self.radius = np.zeros(0)
        self.body_mass = np.zeros(0)
        self.inv_mass = np.zeros(0)
        self.inv_inertia = np.zeros(0)
        self.id = np.zeros(0, np.uint64)
        self.tracking_id = np.zeros(0, np.uint64)
        self.mass = np.zeros(0)
        self.grade = np.zeros(0)
        self.hardness = np.zeros(0)
        self.f = np.zeros((0, N_CLASSES))
        self.entry_time = np.zeros(0)
        self._reset_lists()
        self._dirty = True

    def _reset_lists(self):
        self.start = np.zeros(1, np.int64)
        self.nbr = np.zeros(0, np.int64)
        self.ht = np.zeros(0)
        self.hr = np.zeros(0)
        self.hn = np.zeros(0)
        self.wall_start = np.zeros(1, np.int64)
        self.wall = np.zeros(0, np.int64)
        self.wall_ht = np.zeros(0)
        self.wall_hr = np.zeros(0)
        self.wall_hn = np.zeros(0)
        self.ref_pos = np.zeros((0, 2))
        self.candidates = np.zeros(0, np.int64)
        self._new_to_old = np.zeros(0, np.int64)
        self._pairs = None

    @property
    def n(self) -> int:
        """Number of disks held."""
        return int(self.pos.shape[0])

    @property
    def stable_dt(self) -> float:
        """Stability limit [s]: t_c / dt_safety_factor (see ``DemConfig``)."""
        return self.cfg.stable_dt

    def set_dt(self, dt: float, force: bool = False) -> None:
        """Set the time step [s]; above ``stable_dt`` only with ``force=True``."""
        dt = float(dt)
        if not math.isfinite(dt) or dt <= 0:
            raise ValidationError("dt", "finite and > 0 s", f"got {dt!r}")
        if self.nonsmooth:  # time-implicit: no stability limit
            if dt > 1.0:
                raise ValidationError("dt", "<= 1 s for the nonsmooth method", f"got {dt!r}")
            self.dt = dt
            return
        if dt > self.stable_dt * (1 + 1e-12) and not force:
            raise ValidationError(
                "dt", f"<= the stability limit {self.stable_dt:.4g} s",
                f"got {dt:.4g} s; limit = t_c / {self.cfg.dt_safety_factor:g} with contact "
                f"time t_c = {self.cfg.contact_time:.4g} s; pass force=True for a stability study")
        self.dt = dt

    def held_mass(self) -> float:
        """Tracked mass in the DEM [kg]."""
        return float(self.mass.sum())

    # --------------------------------------------------------- emission
    def emit(self, mass_kg, grade, hardness, f16, tracking_id, inlet: int = 0, ids=None) -> np.ndarray:
        """Put incoming material into the DEM at ``inlet``; return the particle ids (uint64).

        Without ``ids``, ``mass_kg`` is the mass [kg] of one lot that is
        split into pseudo-particles (see ``emitter``); with ``ids``,
        ``mass_kg`` gives one mass per id and each id becomes one disk.
        ``grade`` [-] in [0, 1], ``hardness`` [-] > 0, ``f16`` (16,) or
        (N, 16) size fractions and ``tracking_id`` (uint64) are scalars or
        one per particle. The whole call is validated before anything is
        added.
        """
        if not (isinstance(inlet, (int, np.integer)) and 0 <= inlet < len(self.cfg.inlets)):
            raise ValidationError("inlet", f"an index in [0, {len(self.cfg.inlets) - 1}]",
                                  f"got {inlet!r}")
        if ids is None:
            lot = check_finite_range("mass_kg", mass_kg, 0.0, low_open=True, unit="kg")
            if lot.ndim != 0:
                raise ValidationError("mass_kg", "a scalar lot mass when ids is None",
                                      f"got shape {lot.shape}")
            masses = emitter.split_lot(self.cfg, float(lot), self.rng)
        else:
            masses = np.atleast_1d(np.asarray(mass_kg, dtype=np.float64)).ravel()
            if masses.size == 1:
                masses = np.full(np.asarray(ids).size, masses[0])
        rows = self._validated(masses, grade, hardness, f16, tracking_id, ids)
        radius = self.cfg.diameter_of_mass(rows["mass"]) / 2.0
        pos = emitter.inlet_positions(self.cfg, int(inlet), radius, self.pos, self.radius)
        vel = np.zeros((radius.size, 2))
        vel[:, 1] = -self.cfg.inlet_velocity
        if self._energy_budget is not None:
            # emitted disks never overlap: they bring kinetic and potential energy only
            body = self.cfg.sphere_mass(2.0 * radius)
            self._energy_budget += float((body * (0.5 * self.cfg.inlet_velocity ** 2
                                                  + GRAVITY * pos[:, 1])).sum())
        return self._append(rows, pos, vel)

    def place(self, positions, mass_kg, grade, hardness, f16, tracking_id, ids=None) -> np.ndarray:
        """Put disks at rest at ``positions`` (N, 2) [m] (initial scenes, e.g. a
        packed pile); one disk per row, arguments as in ``emit`` with ids.
        Overlaps are the caller's business. Returns the ids (uint64)."""
        positions = check_finite_range("positions", positions, unit="m")
        if positions.ndim != 2 or positions.shape[1] != 2:
            raise ValidationError("positions", "an (N, 2) array [m]", f"got {positions.shape}")
        masses = np.atleast_1d(np.asarray(mass_kg, dtype=np.float64)).ravel()
        if masses.size == 1:
            masses = np.full(positions.shape[0], masses[0])
        if masses.size != positions.shape[0]:
            raise ValidationError("mass_kg", f"a scalar or {positions.shape[0]} masses",
                                  f"got {masses.size}")
        rows = self._validated(masses, grade, hardness, f16, tracking_id, ids)
        # placed disks may overlap: the guard checks after the next step and takes
        # the energy budget afresh
        self._energy_budget = None
        self._steps_since_check = _CHECK_NOW
        return self._append(rows, positions, np.zeros_like(positions))

    def _validated(self, masses, grade, hardness, f16, tracking_id, ids) -> dict:
        """Check one batch as a whole; return its per-particle columns."""
        masses = check_finite_range("mass_kg", masses, 0.0, low_open=True, unit="kg")
        count = masses.size
        if ids is None:
            new_ids = np.arange(self.next_id, self.next_id + count, dtype=np.uint64)
        else:
            new_ids = np.asarray(ids, dtype=np.uint64).ravel()
            if new_ids.size != count:
                raise ValidationError("ids", f"one id per mass ({count})", f"got {new_ids.size}")
            if np.unique(new_ids).size != count or np.isin(new_ids, self.id).any():
                raise ValidationError("ids", "ids not already in the DEM and not repeated")
        try:
            grade = check_finite_range("grade", np.broadcast_to(grade, (count,)), 0.0, 1.0)
            hardness = check_finite_range("hardness", np.broadcast_to(hardness, (count,)),
                                          0.0, low_open=True)
            f16 = check_fractions(np.broadcast_to(f16, (count, N_CLASSES)), "f16")
            tracking = np.broadcast_to(np.asarray(tracking_id, dtype=np.uint64), (count,))
        except ValidationError:
            raise
        except ValueError as exc:
            raise ValidationError("emit", f"scalars or arrays of length {count}", str(exc)) from None
        return {"id": new_ids, "mass": masses.astype(np.float64), "grade": grade,
                "hardness": hardness, "f": f16 / f16.sum(axis=1, keepdims=True),
                "tracking_id": tracking}

    def _append(self, rows: dict, pos: np.ndarray, vel: np.ndarray) -> np.ndarray:
        count = rows["mass"].size
        diameter = self.cfg.diameter_of_mass(rows["mass"])
        radius = diameter / 2.0
        body = self.cfg.sphere_mass(diameter)
        old_n = self.n
        self.pos = np.concatenate((self.pos, pos))
        self.vel = np.concatenate((self.vel, vel))
        self.omega = np.concatenate((self.omega, np.zeros(count)))
        self.radius = np.concatenate((self.radius, radius))
        self.body_mass = np.concatenate((self.body_mass, body))
        self.inv_mass = np.concatenate((self.inv_mass, 1.0 / body))
        self.inv_inertia = np.concatenate((self.inv_inertia, 1.0 / (0.4 * body * radius ** 2)))
        for name in ("id", "tracking_id", "mass", "grade", "hardness", "f"):
            setattr(self, name, np.concatenate((getattr(self, name), rows[name])))
        self.entry_time = np.concatenate((self.entry_time, np.full(count, self.time)))
        self.emitted_mass += float(rows["mass"].sum())
        if count:
            self._entry_top = max(self._entry_top, float(pos[:, 1].max()))
        if count:
            self.next_id = max(self.next_id, int(rows["id"].max()) + 1)
        self._mark_rows_changed(np.concatenate((np.arange(old_n), np.full(count, -1))))
        return rows["id"].copy()

    def _mark_rows_changed(self, new_to_old: np.ndarray) -> None:
        """Rows changed (``new_to_old[i]``: previous row of row i, -1 if new);
        compose it with the mapping kept since the last list build."""
        prev = self._new_to_old
        if prev.size == 0:
            self._new_to_old = np.full(new_to_old.size, -1, np.int64)
        else:
            self._new_to_old = np.where(new_to_old >= 0, prev[np.maximum(new_to_old, 0)], -1)
        self._dirty = True

    # ---------------------------------------------------------- feeder
    def set_discharge_rate(self, rate_kg_s: float, outlet: int = 0) -> float:
        """Command the feeder of ``outlet`` to ``rate_kg_s`` [kg/s]
        (0..max_discharge_rate); return the rate it will draw [kg/s].

        A feeder cannot draw more than its opening passes: the rate drawn is
        the setpoint capped at ``cfg.orifice_capacity()`` (Beverloo). A
        capped setpoint is reported in ``feeder_state()`` and with a
        ``FeederCapped`` warning (once per outlet and capped setpoint).
        """
        if not (isinstance(outlet, (int, np.integer)) and 0 <= outlet < self.rates.size):
            raise ValidationError("outlet", f"an index in [0, {self.rates.size - 1}]",
                                  f"got {outlet!r}")
        rate = float(rate_kg_s)
        limit = self.cfg.max_discharge_rate
        if not math.isfinite(rate) or not 0.0 <= rate <= limit:
            raise ValidationError("discharge_rate", f"in [0, {limit:g}] kg/s", f"got {rate_kg_s!r}")
        capacity = self.cfg.orifice_capacity()
        applied = min(rate, capacity)
        if applied < rate and self.setpoints[outlet] != rate:
            warnings.warn(FeederCapped(
                f"outlet {outlet}: setpoint {rate:.6g} kg/s capped at {capacity:.6g} kg/s, what "
                f"its {self.cfg.outlet_width:g} m opening passes (Beverloo, "
                f"C = {self.cfg.beverloo_c:g}, k = {self.cfg.beverloo_k:g})"), stacklevel=2)
        self.setpoints[outlet] = rate
        self.rates[outlet] = applied
        return applied

    def feeder_state(self, outlet: int = 0) -> dict:
        """``setpoint`` and drawn ``rate`` [kg/s] of ``outlet``, its opening's
        ``capacity`` [kg/s] (``cfg.orifice_capacity``) and whether ``capped``."""
        setpoint, rate = float(self.setpoints[outlet]), float(self.rates[outlet])
        return {"setpoint": setpoint, "rate": rate, "capacity": self.cfg.orifice_capacity(),
                "capped": rate < setpoint}

    def discharged(self) -> dict:
        """Records of the particles removed by the feeders since the last call.

        Dict of arrays: ``id``, ``tracking_id`` (uint64), ``mass`` [kg],
        ``grade``, ``hardness``, ``f`` (M, 16), ``entry_time`` [s],
        ``time`` [s] of removal, ``outlet`` index; in order of removal.
        """
        out = {k: np.concatenate([r[k] for r in self._records]) for k in _RECORD_FIELDS}
        self._records = [_empty_records()]
        return out

    # --------------------------------------------------------- stepping
    def _rebuild(self) -> None:
        new_to_old = self._new_to_old
        skin = self.cfg.skin
        if self.nonsmooth and self.n:
            # the lists must hold every pair a disk reaches within a step (nonsmooth.run_steps)
            fastest = float(np.sqrt((self.vel ** 2).sum(axis=1)).max())
            skin = max(skin, 2.2 * self.dt * (fastest + GRAVITY * self.dt))
        self._skin = skin
        self.start, self.nbr, self.ht, self.hr, self.hn = kernels.build_pair_list(
            self.pos, self.radius, skin, self.start, self.nbr, self.ht, self.hr, self.hn,
            new_to_old)
        self.wall_start, self.wall, self.wall_ht, self.wall_hr, self.wall_hn = \
            kernels.build_wall_list(self.pos, self.radius, skin, self.walls, self.wall_start,
                                    self.wall, self.wall_ht, self.wall_hr, self.wall_hn,
                                    new_to_old)
        self.candidates = kernels.zone_candidates(self.pos, self._zone_lo, self._zone_hi,
                                                  self._zone_top, skin)
        self.ref_pos = self.pos.copy()
        self._pairs = None
        self._new_to_old = np.arange(self.n, dtype=np.int64)
        self._dirty = False
        self.list_builds += 1

    def step(self, n_steps: int = 1) -> None:
        """Advance ``n_steps`` time steps of ``dt``."""
        remaining = int(n_steps)
        if remaining < 0:
            raise ValidationError("n_steps", ">= 0", f"got {n_steps!r}")
        if self.failure is not None:
            raise self.failure
        before = numba.get_num_threads()
        numba.set_num_threads(self.kernel_threads())
        try:
            self._step(remaining)
        finally:
            numba.set_num_threads(before)

    def kernel_threads(self) -> int:
        """Threads the explicit kernels run on now: ``threads`` (from
        ``cfg.threads``; 0: all of numba's), one below
        ``kernels.PARALLEL_MIN_DISKS`` disks and for the nonsmooth method."""
        if self.nonsmooth or self.n < kernels.PARALLEL_MIN_DISKS:
            return 1
        most = numba.config.NUMBA_NUM_THREADS
        return most if self.threads == 0 else min(self.threads, most)

    def _step(self, remaining: int) -> None:
        removed = np.empty(64, np.int64)
        guard_steps = max(1, int(round(GUARD_INTERVAL / self.dt)))
        while remaining > 0:
            if self.n == 0:
                self.time += remaining * self.dt
                self.steps_done += remaining
                self.credits[:] = np.minimum(self.credits + self.rates * remaining * self.dt,
                                             self.credit_cap)
                return
            if self._dirty:
                self._rebuild()
            chunk = min(remaining, max(guard_steps - self._steps_since_check, 1))
            if self.nonsmooth:
                done, self.time, n_removed, moved, bad_row, bad_kind = nonsmooth.run_steps(
                    chunk, self.dt, self.time, self.pos, self.vel, self.omega, self.radius,
                    self.inv_mass, self.inv_inertia, self.start, self.nbr, self.hn, self.ht,
                    self.hr, self.wall_start, self.wall, self.wall_hn, self.wall_ht,
                    self.wall_hr, self.walls, self.params, self.solver, self.ref_pos,
                    0.5 * self._skin, self.candidates, self._zone_lo, self._zone_hi,
                    self._zone_top, self.rates, self.credits, self.credit_cap, self.mass,
                    removed, self.speed_limit, self._box, self.solver_stats)
            else:
                force, torque = self._buffers()
                pair_force, pair_torque, rev_start, rev_pair = self._pair_buffers()
                done, self.time, n_removed, moved, bad_row, bad_kind = kernels.run_steps(
                    chunk, self.dt, self.time, self.pos, self.vel, self.omega,
                    force, torque, self.radius, self.body_mass,
                    self.inv_mass, self.inv_inertia, self.start, self.nbr, self.ht, self.hr,
                    self.wall_start, self.wall, self.wall_ht, self.wall_hr, self.walls,
                    self.params, self.ref_pos, 0.5 * self._skin, self.candidates, self._zone_lo,
                    self._zone_hi, self._zone_top, self.rates, self.credits, self.credit_cap,
                    self.mass, removed, self.speed_limit, self._box, pair_force, pair_torque,
                    rev_start, rev_pair)
            remaining -= done
            self.steps_done += done
            self._steps_since_check += done
            if n_removed:
                self._remove(removed[:n_removed].copy())
            if moved:
                self._dirty = True
            if bad_kind != kernels.GUARD_NONE:
                self._fail(*self._seen_at_row(bad_row, bad_kind))
            if self._steps_since_check >= guard_steps:
                self._steps_since_check = 0
                self._check_energy_and_overlap()

    # ------------------------------------------------------------ guard
    @property
    def speed_limit(self) -> float:
        """Speed [m/s] above which a disk has blown up: ``guard_speed_factor``
        times the free-fall speed from the highest point a disk entered at."""
        fall = math.sqrt(self.cfg.inlet_velocity ** 2 + 2.0 * GRAVITY * max(self._entry_top, 0.0))
        return self.cfg.guard_speed_factor * fall

    def _seen_at_row(self, row: int, kind: int):
        x, y = self.pos[row]
        speed = float(np.hypot(*self.vel[row]))
        if kind == kernels.GUARD_SPEED:
            return "speed", (f"disk id {int(self.id[row])} at {speed:.4g} m/s, above the limit "
                             f"{self.speed_limit:.4g} m/s ({self.cfg.guard_speed_factor:g} x the "
                             "free-fall speed from the highest entry point)")
        fast = int((np.hypot(self.vel[:, 0], self.vel[:, 1]) > self.speed_limit).sum())
        return "outside", (f"disk id {int(self.id[row])} outside the container at x = {x:.4g} m, "
                           f"y = {y:.4g} m (container x in [{self._box[0]:.4g}, "
                           f"{self._box[1]:.4g}] m, y >= {self._box[2]:.4g} m), moving at "
                           f"{speed:.4g} m/s; {fast} disk(s) above the speed limit")

    def _check_energy_and_overlap(self) -> None:
        if self.n == 0:
            return
        energy = self.energy()
        # the nonsmooth method has no contact springs: a penetration its sweeps leave
        # is an error of the solve (it compresses), not stored energy
        total = energy["total"] - energy["elastic"] if self.nonsmooth else energy["total"]
        if self._energy_budget is None or not math.isfinite(self._energy_budget):
            self._energy_budget = total
        scale = max(abs(self._energy_budget),
                    float(self.body_mass.sum()) * GRAVITY * self.cfg.diameter_max)
        limit = self._energy_budget + self.cfg.guard_energy_growth * scale
        if not total <= limit:
            self._fail("energy", f"mechanical energy {total:.4g} J above the budget "
                                 f"{self._energy_budget:.4g} J (what it held at the first check, "
                                 f"plus what entered, minus what left) by more than "
                                 f"{self.cfg.guard_energy_growth:g} x {scale:.4g} J")
        overlap = self.max_overlap_ratio()
        if not overlap <= self.cfg.guard_overlap_ratio:
            self._fail("overlap", f"an overlap of {overlap:.3g} of the smaller diameter (limit "
                                  f"{self.cfg.guard_overlap_ratio:g})")

    def _fail(self, kind: str, seen: str) -> None:
        ratio = self.dt / self.stable_dt
        if self.nonsmooth:
            cause = (f"the nonsmooth solver ({self.cfg.solver_iterations} sweeps, step "
                     f"{self.dt:.4g} s) did not hold the contacts: disks placed deep in each "
                     "other or in a wall, or too few sweeps for the scene")
        elif ratio > 1 + 1e-12:
            cause = (f"the time step {self.dt:.4g} s is {ratio:.3g} x the stability limit "
                     f"{self.stable_dt:.4g} s (forced): explicit integration of the contacts "
                     "diverged")
        else:
            cause = (f"the time step {self.dt:.4g} s is within the stability limit "
                     f"{self.stable_dt:.4g} s, so look at the scene: disks placed deep in "
                     "each other or in a wall, or a stiffness the limit does not cover")
        self.failure = DemBlowUp(kind, seen, self.time, self.steps_done, cause)
        raise self.failure

    def advance(self, seconds: float) -> None:
        """Advance by ``seconds`` [s], rounded up to whole steps."""
        seconds = float(seconds)
        if not math.isfinite(seconds) or seconds < 0:
            raise ValidationError("seconds", "finite and >= 0 s", f"got {seconds!r}")
        self.step(int(math.ceil(seconds / self.dt - 1e-9)))

    def _pair_buffers(self):
        """Per-pair scratch arrays and the partner side of the pair list
        (``kernels.compute_forces``), made again after each list build."""
        if self._pairs is None:
            self._pairs = (np.zeros((self.nbr.size, 2)), np.zeros(self.nbr.size),
                           *kernels.reverse_pairs(self.start, self.nbr))
        return self._pairs

    def _buffers(self):
        """Force (N, 2) and torque (N,) scratch arrays sized to the disks held."""
        if getattr(self, "_force", None) is None or self._force.shape[0] != self.n:
            self._force = np.zeros((self.n, 2))
            self._torque = np.zeros(self.n)
        return self._force, self._torque

    def _remove(self, rows: np.ndarray) -> None:
        """Take the feeder-removed ``rows`` out, recording them as discharged."""
        outlet = np.array([int(np.flatnonzero((self._zone_lo <= self.pos[r, 0])
                                              & (self.pos[r, 0] <= self._zone_hi))[0])
                           for r in rows], dtype=np.int64)
        record = {"id": self.id[rows], "tracking_id": self.tracking_id[rows],
                  "mass": self.mass[rows], "grade": self.grade[rows],
                  "hardness": self.hardness[rows], "f": self.f[rows],
                  "entry_time": self.entry_time[rows], "time": np.full(rows.size, self.time),
                  "outlet": outlet}
        self._records.append({k: np.array(v) for k, v in record.items()})
        self.discharged_mass += float(record["mass"].sum())
        if self._energy_budget is not None:
            # their springs' energy leaves too, so the budget stays an upper bound
            self._energy_budget -= float((self.body_mass[rows] * (
                0.5 * (self.vel[rows] ** 2).sum(axis=1) + GRAVITY * self.pos[rows, 1])).sum()
                + 0.5 * (self.omega[rows] ** 2 / self.inv_inertia[rows]).sum())
        keep = np.ones(self.n, bool)
        keep[rows] = False
        for name in _PARTICLE_FIELDS:
            setattr(self, name, getattr(self, name)[keep])
        self._mark_rows_changed(np.flatnonzero(keep))

    # -------------------------------------------------------- read-outs
    def snapshot(self) -> dict:
        """Copy of the particle state at ``time``.

        Keys: ``time`` [s] (scalar), ``id``, ``tracking_id`` (uint64),
        ``position`` (N, 2) [m], ``velocity`` (N, 2) [m/s], ``omega`` [rad/s],
        ``radius`` [m], ``mass`` [kg] (tracked), ``grade``, ``hardness``,
        ``f`` (N, 16), ``entry_time`` [s], ``residence_time`` [s].
        """
        return {"time": np.float64(self.time), "id": self.id.copy(),
                "tracking_id": self.tracking_id.copy(), "position": self.pos.copy(),
                "velocity": self.vel.copy(), "omega": self.omega.copy(),
                "radius": self.radius.copy(), "mass": self.mass.copy(),
                "grade": self.grade.copy(), "hardness": self.hardness.copy(),
                "f": self.f.copy(), "entry_time": self.entry_time.copy(),
                "residence_time": self.time - self.entry_time}

    def energy(self) -> dict:
        """Kinetic, gravitational (about y = 0) and spring energy [J] and their total."""
        if self._dirty and self.n:
            self._rebuild()
        kinetic = float(0.5 * (self.body_mass * (self.vel ** 2).sum(axis=1)).sum()
                        + 0.5 * (self.omega ** 2 / self.inv_inertia).sum())
        potential = float((self.body_mass * GRAVITY * self.pos[:, 1]).sum())
        # the nonsmooth method keeps impulses, not tangential springs: its elastic
        # energy is that of the normal compliance
        ht = np.zeros_like(self.ht) if self.nonsmooth else self.ht
        wall_ht = np.zeros_like(self.wall_ht) if self.nonsmooth else self.wall_ht
        elastic = float(kernels.elastic_energy(self.pos, self.radius, self.start, self.nbr,
                                               self.wall_start, self.wall, self.walls, ht,
                                               wall_ht, self.params)) if self.n else 0.0
        return {"kinetic": kinetic, "potential": potential, "elastic": elastic,
                "total": kinetic + potential + elastic}

    def max_overlap_ratio(self) -> float:
        """Largest disk-disk overlap over the smaller diameter [-]."""
        if self._dirty and self.n:
            self._rebuild()
        return float(kernels.max_overlap_ratio(self.pos, self.radius, self.start, self.nbr))

    def overlap_stats(self) -> tuple[float, float]:
        """Mean and largest disk-disk overlap over the smaller diameter [-] of the
        touching pairs (0, 0 without any)."""
        if not self.n:
            return 0.0, 0.0
        if self._dirty:
            self._rebuild()
        i = np.repeat(np.arange(self.n), np.diff(self.start))
        j = self.nbr
        delta = self.radius[i] + self.radius[j] - np.hypot(*(self.pos[i] - self.pos[j]).T)
        ratio = delta / (2 * np.minimum(self.radius[i], self.radius[j]))
        touching = ratio[ratio > 0]
        return (float(touching.mean()) if touching.size else 0.0,
                float(touching.max()) if touching.size else 0.0)

    def mass_balance_error(self) -> float:
        """|emitted - held - discharged| / emitted [-] (0 when nothing entered)."""
        if self.emitted_mass == 0:
            return 0.0
        return abs(self.emitted_mass - self.held_mass() - self.discharged_mass) / self.emitted_mass

    # ------------------------------------------------------ checkpoints
    def save_checkpoint(self, path) -> None:
        """Write the complete state (including contact history and pending
        discharge records) to ``path`` (.npz); ``load_checkpoint`` continues
        bit-for-bit."""
        meta = {"config": self.cfg.to_dict(), "time": self.time, "dt": self.dt,
                "steps_done": self.steps_done, "next_id": self.next_id,
                "emitted_mass": self.emitted_mass, "discharged_mass": self.discharged_mass,
                "rng": self.rng.bit_generator.state, "dirty": self._dirty,
                "list_builds": self.list_builds, "entry_top": self._entry_top,
                "energy_budget": self._energy_budget,
                "steps_since_check": self._steps_since_check, "skin": self._skin}
        arrays = {name: getattr(self, name) for name in _PARTICLE_FIELDS + _LIST_FIELDS}
        arrays["new_to_old"] = self._new_to_old
        arrays["rates"] = self.rates
        arrays["solver_stats"] = self.solver_stats
        arrays["setpoints"] = self.setpoints
        arrays["credits"] = self.credits
        pending = {k: np.concatenate([r[k] for r in self._records]) for k in _RECORD_FIELDS}
        arrays.update({f"record_{k}": v for k, v in pending.items()})
        with open(path, "wb") as handle:
            np.savez_compressed(handle, meta=np.array(json.dumps(meta)), **arrays)

    @classmethod
    def load_checkpoint(cls, path, changes: dict | None = None) -> "Dem":
        """Rebuild a ``Dem`` from ``save_checkpoint`` output. With ``changes``
        (``DemConfig`` fields, e.g. ``{"method": "nonsmooth"}`` or a
        stiffness) that alter the configuration, the same state continues
        under the changed one at its default step, with the contact history
        cleared (springs and impulses of another law mean nothing here): the
        way to run both methods, or both stiffnesses, from one pile."""
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            cfg = DemConfig.from_dict(meta["config"])
            changed = DemConfig.from_dict({**cfg.to_dict(), **(changes or {})})
            switch = changed != cfg
            cfg = changed
            dem = cls(cfg)
            if not switch:
                dem.dt = float(meta["dt"])
            dem.time = float(meta["time"])
            dem.steps_done = int(meta["steps_done"])
            dem.next_id = int(meta["next_id"])
            dem.emitted_mass = float(meta["emitted_mass"])
            dem.discharged_mass = float(meta["discharged_mass"])
            dem.rng.bit_generator.state = meta["rng"]
            dem._dirty = bool(meta["dirty"])
            dem.list_builds = int(meta["list_builds"])
            dem._entry_top = float(meta.get("entry_top", max(
                [dem._entry_top] + data["pos"][:, 1].tolist())))
            dem._energy_budget = meta.get("energy_budget")
            dem._steps_since_check = int(meta.get("steps_since_check", 0))
            dem._skin = float(meta.get("skin", dem.cfg.skin))
            if switch:
                for name in ("ht", "hr", "hn", "wall_ht", "wall_hr", "wall_hn"):
                    getattr(dem, name)[:] = 0.0
                dem._dirty = True  # lists sized for the new method's reach
            if "solver_stats" in data.files:  # older checkpoints hold fewer counters
                saved = data["solver_stats"]
                dem.solver_stats[:saved.size] = saved
            for name in _PARTICLE_FIELDS + _LIST_FIELDS:
                if name in ("hn", "wall_hn") and name not in data.files:
                    # a checkpoint of the explicit DEM from before the nonsmooth one
                    setattr(dem, name, np.zeros_like(data[name[:-1] + "t"]))
                    continue
                setattr(dem, name, data[name].copy())
            dem._new_to_old = data["new_to_old"].copy()
            dem.rates = data["rates"].copy()
            dem.setpoints = (data["setpoints"].copy() if "setpoints" in data.files
                             else dem.rates.copy())
            dem.credits = data["credits"].copy()
            dem._records = [{k: data[f"record_{k}"].copy() for k in _RECORD_FIELDS}]
        return dem
