"""DEM configuration: geometry, material, particle sizes and time-step rule.

All values are SI. The defaults describe the paper's stockpile (section
"Simulator": a 60 m tall pile holding up to 2,000 t in ~20,000 pseudo-
particles, i.e. ~100 kg each) in 2D: a wide floor with low kerb walls (free
slopes), two inlets above the pile and one outlet with a feeder in the floor.

Contact model (see ``surrogate/dem/README.md`` for the full equations)
----------------------------------------------------------------------
Linear spring-dashpot normal force ``F_n = k_n delta + c_n d(delta)/dt``
(clipped at 0, minus an optional constant cohesion pull), damping
``c_n = 2 zeta sqrt(k_n m_eff)`` with ``zeta`` chosen so that a binary impact
rebounds with the configured restitution *including* the force clipping
(Schwager & Poeschel 2007, Granular Matter 9:465); tangential spring
``k_t`` with Coulomb limit ``mu F_n`` and contact history; elastic-plastic
rolling resistance (Ai et al. 2011, Powder Technol. 206:269, model C) with
rolling stiffness ``k_r = 2.25 k_n mu_r^2 R_eff^2`` and limit
``mu_r R_eff F_n``.

Time step
---------
Contact duration of the linear spring for the stiffest, lightest pair (two
smallest disks): ``t_c = pi sqrt(m_eff,min / k_n)`` with
``m_eff,min = m(d_min) / 2`` (undamped half period, e.g. Cundall & Strack
1979; O'Sullivan & Bray 2004 for the safety margin). The stability limit
accepted without ``force`` is ``stable_dt = t_c / dt_safety_factor``.
Symplectic Euler on a single linear contact is unstable above
``dt = (2 / pi) t_c``; in a dense packing each disk has several contacts and
the limit is much lower: on the settled 20,000-disk pile under the hardest
load of the paper design (feeder and inflow at 2 t/s), runs of 4 s were
stable at 0.22 t_c and blew up at 0.26 t_c (``benchmarks/bench_dem_step.py``).
The default factor 15 (dt = 0.067 t_c) stays 3.3x under the largest step
measured stable and 3.9x under the smallest measured unstable one; the
smallest factor accepted, 5 (0.2 t_c), leaves 1.1x.

Blow-up guard
-------------
Every step the DEM checks each disk's speed against ``guard_speed_factor``
times the free-fall speed from the highest point anything entered at
(``sqrt(v_inlet^2 + 2 g h)``) and that its centre lies inside the container
(the bounding box of the walls, widened by ``diameter_max``; never below
it); every ``GUARD_INTERVAL`` seconds of simulated time
(``simulation.py``) it checks the mechanical energy (kinetic + potential
about the floor + elastic) against the energy it held at the first check
plus what entered minus what the feeders took (a dissipative system never
gains energy), and the largest overlap. A run that fails stops with
``DemBlowUp`` naming what was seen, when, and why. The nonsmooth method
keeps no contact springs, so its energy check leaves the elastic term out (a
penetration its sweeps leave is an error of the solve, not stored energy).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from cosim.errors import ValidationError
from cosim.numerics import cbrt, power

GRAVITY = 9.81
"""Gravitational acceleration [m/s^2], along -y."""

METHODS = ("explicit", "nonsmooth")
"""DEM methods (``DemConfig.method``)."""

PACKING_FRACTION = 0.82
"""Area fraction of a random dense packing of these polydisperse disks [-]."""

BEVERLOO_C = 0.66
"""Default discharge constant C of the 2D Beverloo law [-] (``orifice_capacity``,
with k = 1.5), measured on this DEM's own orifice flow with the default
material: a bunker emptying through a 4 and a 5 m opening in a raised floor,
two seeds each, gave C = 0.71, 0.53 (intermittent arches), 0.69, 0.69; mean
0.66, standard deviation 0.08 (``examples/dem_orifice.py``). Openings of
2.5 m and less jam within seconds (arches of these rough disks)."""

MIN_RESTITUTION = 0.25
"""Smallest restitution a clipped linear dashpot reaches with zeta <= 0.6."""


def _integer_in(name: str, value, low: int, high: int, note: str = "") -> int:
    """``value`` as an int, refused by name unless an integer in [low, high]."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) \
            or not low <= value <= high:
        raise ValidationError(name, f"an integer in [{low}, {high}]{note}", f"got {value!r}")
    return int(value)


def _pairs(value, name):
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < 1:
        raise ValidationError(name, "a list of [x, y] pairs [m]", f"got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValidationError(name, "finite coordinates [m]")
    return arr


@dataclass
class DemConfig:
    """Parameters of the 2D stockpile DEM (SI units; defaults in brackets).

    Geometry
    --------
    floor_width : float
        Width of the floor [m] (160), centred on x = 0, at y = 0.
    side_wall_height : float
        Height of the vertical walls at both floor ends [m] (3: kerbs, so the
        pile's slopes are free; set >= pile height for a bunker).
    extra_walls : list of [ax, ay, bx, by]
        Additional static wall segments [m] (none), e.g. hopper sides or an
        incline.
    inlets : list of [x, y]
        Inlet points above the pile [m] ([[-2, 62], [2, 62]]).
    inlet_width : float
        Width of the inlet stream [m] (1.0): emitted disks are laid in rows
        this wide above the inlet point.
    inlet_velocity : float
        Downward speed of emitted material [m/s] (2.0, a belt discharge).
    outlets : list of float
        x of the outlet centres in the floor [m] ([0.0]).
    outlet_width : float
        Width of each outlet opening [m] (8.0). The 2D Beverloo estimate
        W = C rho_2D sqrt(g) (b - k d)^1.5 with rho_2D ~ 530 kg/m^2 asks for
        b ~ 2 m at 2 t/s; a feeder drawing from a shallow zone needs more:
        in the 600-disk discharge test 4 m delivered 1.7 t/s, 6 m 1.87 t/s
        (arches starve the zone), 8 m holds 2 t/s within 1 %.
    feeder_zone_height : float
        Height above the floor of the zone from which the feeder draws [m]
        (1.0, about two layers of disks).
    max_discharge_rate : float
        Largest feeder rate setpoint [kg/s] (2000; paper: 2 t/s).
    beverloo_c, beverloo_k : float
        Constants of the orifice capacity that bounds each feeder
        (``orifice_capacity``) [-] (C = BEVERLOO_C, k = 1.5).

    Material
    --------
    density : float
        Solid density of the disks [kg/m^3] (2700, granite-like ore). A disk
        of diameter d has the mass of a sphere, ``density pi d^3 / 6``.
    normal_stiffness : float
        Linear normal spring k_n [N/m] (4e7). Chosen as low as realistic:
        at the base of a 60 m pile the mean contact force is about
        rho_b g H d ~ 1.2e5 N, a mean overlap of ~1 % of the mean diameter
        (0.34 m); in the settled 20,000-disk pile the median overlap is
        0.08 % and the 99th percentile 1.2 % (README.md).
    tangential_stiffness_ratio : float
        k_t / k_n [-] (2/7, the ratio that gives equal normal and tangential
        oscillation periods for spheres).
    friction : float
        Coulomb friction coefficient mu, particle-particle and wall [-] (0.8,
        angular crushed rock).
    rolling_resistance : float
        Rolling resistance coefficient mu_r [-] (0.6). High on purpose: in 2D
        round disks stand in for angular ore, and the rolling resistance
        carries the interlocking of the real shapes. With mu = 0.8 and
        mu_r = 0.6 poured 600-disk piles stand at 35-39 degrees (mean of both
        flanks, seeds 0-3: 35.3, 35.8, 38.9, 36.8; 30-40 degrees is the target for crushed ore; see
        tests/test_dem_physics.py and README.md).
    restitution : float
        Normal coefficient of restitution e in [0.25, 1] [-] (0.3).
    cohesion : float
        Constant attractive force per contact while in contact [N] (0).

    Particles and integration
    -------------------------
    diameter_min, diameter_max : float
        Disk diameter range [m] (0.2, 0.48).
    skin : float
        Verlet-list skin [m] (0.05); lists are rebuilt when a disk has moved
        more than skin / 2 since the last build.
    dt_safety_factor : float
        stable_dt = t_c / dt_safety_factor [-] (15, >= 5): 0.067 t_c, 3.3x
        under the 0.22 t_c measured stable on a dense pile (module docstring).
    threads : int
        Threads of the explicit DEM's force kernel and integration [-] (1;
        0: all of numba's, ``NUMBA_NUM_THREADS``). Any count gives the same
        bits; scenes under ``kernels.PARALLEL_MIN_DISKS`` disks always run on
        one. One by default because a thread that the system deschedules
        stalls every step: on this project's shared 2-core machine at a load
        average of ~9, 2 threads ran a 20,000-disk pile at 0.14x the speed
        of one (``benchmarks/bench_dem_threads.py``, README "Threads").

    Method
    ------
    method : str
        ``"explicit"`` (the smooth spring-dashpot DEM, ``kernels.py``) or
        ``"nonsmooth"`` (time-implicit, ``nonsmooth.py``; Servin et al. 2014)
        ("explicit").
    nonsmooth_dt : float
        Default time step of the nonsmooth method [s] (0.011, the paper's);
        it has no stability limit.
    solver_iterations : int
        Most projected Gauss-Seidel sweeps per nonsmooth step [-] (100, the
        paper's).
    solver_tolerance : float
        A sweep whose largest velocity change is below this ends the solve
        [m/s] (1e-6).
    stabilization_steps : float
        Nonsmooth penetration relaxation time tau in steps [-] (2: a
        penetration beyond the compliance's is removed over about 3 steps).
    impact_speed : float
        Approach speed above which a nonsmooth contact obeys Newton's impact
        law with ``restitution`` [m/s] (0.5; above g h = 0.11 m/s at 11 ms,
        so resting contacts stay inelastic).
    missed_contact_resolves : int
        Most times a nonsmooth step is solved again for contacts its solve
        closed but that were not rows (``nonsmooth.py``, item 6) [-] (3, in
        [0, 100]; 0 switches the check off, the solver before it).
    solver_relaxation : float
        Over-relaxation factor omega of the normal impulses in the sweeps [-]
        (1: projected Gauss-Seidel, the paper's; in (0, 2): projected successive
        over-relaxation, Cryer 1971, ``nonsmooth.py`` item 5).

    Blow-up guard (module docstring)
    --------------------------------
    guard_speed_factor : float
        A disk faster than this times the free-fall speed from the highest
        entry point has blown up [-] (2.0, > 1).
    guard_energy_growth : float
        Largest gain of mechanical energy over the budget, as a fraction of
        the budget [-] (0.5, > 0). Loose on purpose: the symplectic Euler
        energy of a stable contact oscillates by ~ (pi / 2) dt / t_c of its
        kinetic energy; the speed check is the sharp one.
    guard_overlap_ratio : float
        Largest overlap / smaller diameter of a sound run [-] (0.5, in (0, 1]).
    """

    floor_width: float = 160.0
    side_wall_height: float = 3.0
    extra_walls: list = field(default_factory=list)
    inlets: list = field(default_factory=lambda: [[-2.0, 62.0], [2.0, 62.0]])
    inlet_width: float = 1.0
    inlet_velocity: float = 2.0
    outlets: list = field(default_factory=lambda: [0.0])
    outlet_width: float = 8.0
    feeder_zone_height: float = 1.0
    max_discharge_rate: float = 2000.0
    beverloo_c: float = BEVERLOO_C
    beverloo_k: float = 1.5
    density: float = 2700.0
    normal_stiffness: float = 4.0e7
    tangential_stiffness_ratio: float = 2.0 / 7.0
    friction: float = 0.8
    rolling_resistance: float = 0.6
    restitution: float = 0.3
    cohesion: float = 0.0
    diameter_min: float = 0.2
    diameter_max: float = 0.48
    skin: float = 0.05
    dt_safety_factor: float = 15.0
    threads: int = 1
    method: str = "explicit"
    nonsmooth_dt: float = 0.011
    solver_iterations: int = 100
    solver_tolerance: float = 1e-6
    stabilization_steps: float = 2.0
    impact_speed: float = 0.5
    missed_contact_resolves: int = 3
    solver_relaxation: float = 1.0
    guard_speed_factor: float = 2.0
    guard_energy_growth: float = 0.5
    guard_overlap_ratio: float = 0.5

    def __post_init__(self):
        self.inlets = _pairs(self.inlets, "inlets").tolist()
        walls = np.asarray(self.extra_walls, dtype=np.float64).reshape(-1, 4) \
            if len(self.extra_walls) else np.zeros((0, 4))
        if not np.isfinite(walls).all() or (np.hypot(walls[:, 2] - walls[:, 0],
                                                     walls[:, 3] - walls[:, 1]) <= 0).any():
            raise ValidationError("extra_walls", "segments [ax, ay, bx, by] of finite, "
                                  "non-zero length [m]")
        self.extra_walls = walls.tolist()
        outlets = np.atleast_1d(np.asarray(self.outlets, dtype=np.float64))
        if outlets.ndim != 1 or outlets.size < 1 or not np.isfinite(outlets).all():
            raise ValidationError("outlets", "a non-empty list of finite x positions [m]")
        self.outlets = outlets.tolist()
        positive = ("floor_width", "side_wall_height", "inlet_width", "outlet_width",
                    "feeder_zone_height", "density", "normal_stiffness",
                    "tangential_stiffness_ratio", "diameter_min", "diameter_max", "skin")
        for name in positive:
            value = float(getattr(self, name))
            if not math.isfinite(value) or value <= 0:
                raise ValidationError(name, "finite and > 0", f"got {value!r}")
            setattr(self, name, value)
        for name, low, high in (("friction", 0.0, 10.0), ("rolling_resistance", 0.0, 10.0),
                                ("cohesion", 0.0, math.inf), ("inlet_velocity", 0.0, 1e3),
                                ("max_discharge_rate", 0.0, 1e6), ("beverloo_c", 0.0, 10.0),
                                ("beverloo_k", 0.0, 10.0)):
            value = float(getattr(self, name))
            if not math.isfinite(value) and high != math.inf or not low <= value <= high:
                raise ValidationError(name, f"in [{low:g}, {high:g}]", f"got {value!r}")
            setattr(self, name, value)
        if not MIN_RESTITUTION <= float(self.restitution) <= 1.0:
            raise ValidationError("restitution", f"in [{MIN_RESTITUTION:g}, 1]",
                                  f"got {self.restitution!r}; a clipped linear dashpot "
                                  "cannot dissipate more")
        self.restitution = float(self.restitution)
        if self.diameter_max < self.diameter_min:
            raise ValidationError("diameter_max", f">= diameter_min = {self.diameter_min:g} m",
                                  f"got {self.diameter_max!r}")
        if not float(self.dt_safety_factor) >= 5.0:
            raise ValidationError("dt_safety_factor", ">= 5", f"got {self.dt_safety_factor!r}")
        self.dt_safety_factor = float(self.dt_safety_factor)
        if self.method not in METHODS:
            raise ValidationError("method", f"one of {list(METHODS)}", f"got {self.method!r}")
        if self.method == "nonsmooth" and self.cohesion > 0:
            raise ValidationError("cohesion", "0 with method = \"nonsmooth\" (not modelled)",
                                  f"got {self.cohesion!r}")
        self.solver_iterations = _integer_in("solver_iterations", self.solver_iterations, 1,
                                             100_000)
        self.missed_contact_resolves = _integer_in("missed_contact_resolves",
                                                   self.missed_contact_resolves, 0, 100)
        self.threads = _integer_in("threads", self.threads, 0, 4096, note=" (0: all)")
        for name in ("solver_tolerance", "stabilization_steps"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and 0.0 <= value <= 1e3):
                raise ValidationError(name, "in [0, 1000]", f"got {value!r}")
            setattr(self, name, value)
        relaxation = float(self.solver_relaxation)
        if not 0.0 < relaxation < 2.0:  # over-relaxation diverges from 2 on
            raise ValidationError("solver_relaxation", "in (0, 2)", f"got {relaxation!r}")
        self.solver_relaxation = relaxation
        for name, low, high in (("nonsmooth_dt", 0.0, 1.0), ("impact_speed", 0.0, 1e3),
                                ("guard_speed_factor", 1.0, 1e6),
                                ("guard_energy_growth", 0.0, 1e6),
                                ("guard_overlap_ratio", 0.0, 1.0)):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and low < value <= high):
                raise ValidationError(name, f"in ({low:g}, {high:g}]", f"got {value!r}")
            setattr(self, name, value)
        half = self.floor_width / 2
        for x in self.outlets:
            if abs(x) + self.outlet_width / 2 > half - self.diameter_max:
                raise ValidationError("outlets", f"inside the floor |x| + outlet_width/2 < {half:g} m",
                                      f"got {x!r}")
        for x, y in self.inlets:
            if abs(x) > half or y <= 0:
                raise ValidationError("inlets", f"above the floor (|x| <= {half:g} m, y > 0)",
                                      f"got [{x!r}, {y!r}]")

    # ----------------------------------------------------------- derived
    def sphere_mass(self, diameter):
        """Mass [kg] of a disk of ``diameter`` [m]: a sphere of ``density``."""
        return self.density * math.pi / 6.0 * power(diameter, 3.0)

    def diameter_of_mass(self, mass):
        """Diameter [m] of a sphere of ``mass`` [kg], clipped to the size range."""
        d = cbrt(6.0 * np.asarray(mass, dtype=np.float64) / (math.pi * self.density))
        return np.clip(d, self.diameter_min, self.diameter_max)

    @property
    def mean_diameter(self) -> float:
        """Mean disk diameter [m] of disk volumes uniform in [d_min^3, d_max^3]."""
        lo, hi = self.diameter_min, self.diameter_max
        if hi - lo < 1e-12 * hi:
            return hi
        # E[d] = (3/4) (hi^4 - lo^4) / (hi^3 - lo^3)
        return 0.75 * (hi ** 4 - lo ** 4) / (hi ** 3 - lo ** 3)

    @property
    def areal_bulk_density(self) -> float:
        """Bulk mass per area of the 2D pile [kg/m^2]: ``PACKING_FRACTION`` times
        the mean disk (sphere) mass over the mean disk area."""
        lo, hi = self.diameter_min, self.diameter_max
        if hi - lo < 1e-12 * hi:
            d3, d2 = hi ** 3, hi ** 2
        else:
            d3 = 0.5 * (hi ** 3 + lo ** 3)
            d2 = 0.6 * (hi ** 5 - lo ** 5) / (hi ** 3 - lo ** 3)
        return PACKING_FRACTION * self.density * (math.pi / 6.0 * d3) / (math.pi / 4.0 * d2)

    def orifice_capacity(self, width: float | None = None) -> float:
        """Largest mass flow [kg/s] an opening of ``width`` [m] (default
        ``outlet_width``) passes: the 2D form of Beverloo's law (Beverloo,
        Leniger and van de Velde 1961, Chem. Eng. Sci. 15:260, for a slot),
        ``W = C rho_2D sqrt(g) (b - k d)^(3/2)``, with ``rho_2D`` the
        ``areal_bulk_density`` [kg/m^2], ``g`` = 9.81 m/s^2, ``b`` the width
        [m], ``d`` the ``mean_diameter`` [m], ``C = beverloo_c`` and
        ``k = beverloo_k``; 0 when ``b <= k d`` (the opening arches over).
        The defaults are this DEM's own orifice flow (``BEVERLOO_C``): 2.1
        t/s through 2 m, 25 t/s through the default 8 m."""
        b = self.outlet_width if width is None else float(width)
        free = max(b - self.beverloo_k * self.mean_diameter, 0.0)
        return self.beverloo_c * self.areal_bulk_density * math.sqrt(GRAVITY) * free ** 1.5

    @property
    def tangential_stiffness(self) -> float:
        """k_t [N/m]."""
        return self.normal_stiffness * self.tangential_stiffness_ratio

    @property
    def damping_ratio(self) -> float:
        """zeta [-] of the normal dashpot that yields ``restitution`` with clipping."""
        return damping_ratio_for_restitution(self.restitution)

    @property
    def contact_time(self) -> float:
        """t_c = pi sqrt(m_eff,min / k_n) [s] for two disks of ``diameter_min``."""
        m_eff = float(self.sphere_mass(self.diameter_min)) / 2.0
        return math.pi * math.sqrt(m_eff / self.normal_stiffness)

    @property
    def stable_dt(self) -> float:
        """Largest time step accepted without ``force``: t_c / dt_safety_factor [s]."""
        return self.contact_time / self.dt_safety_factor

    # --------------------------------------------------------------- I/O
    def to_dict(self) -> dict:
        """Plain dict (JSON/TOML friendly)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "DemConfig":
        """Build from a dict; unknown keys are refused by name."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValidationError("dem config", f"keys among {sorted(names)}",
                                  f"unknown key(s) {unknown}")
        return cls(**data)

    @classmethod
    def from_toml(cls, path) -> "DemConfig":
        """Read a TOML file; the keys may sit at top level or under ``[dem]``."""
        from cosim.tomlfile import read_toml

        data = read_toml(path, "dem config")
        return cls.from_dict(data.get("dem", data))


def _restitution_with_clipping(zeta: float) -> float:
    """Rebound speed / impact speed of a linear spring-dashpot whose force is
    clipped at zero (contact ends when k delta + c delta' = 0).

    delta(t) = (v0/w) exp(-a t) sin(w t), a = zeta w0, w = w0 sqrt(1 - zeta^2);
    the force vanishes at tan(w t*) = -2 a w / (w0^2 - 2 a^2), w t* in (pi/2, pi].
    """
    w0 = 1.0
    a = zeta * w0
    w = w0 * math.sqrt(1.0 - zeta * zeta)
    phase = math.atan2(2.0 * a * w, -(w0 * w0 - 2.0 * a * a))
    t_end = phase / w
    return -math.exp(-a * t_end) * (math.cos(phase) - (a / w) * math.sin(phase))


def damping_ratio_for_restitution(e: float) -> float:
    """Damping ratio zeta with the clipped-force restitution equal to ``e``.

    Without clipping zeta = -ln e / sqrt(pi^2 + ln^2 e); clipping makes the
    contact end earlier, so zeta is found by bisection on
    ``_restitution_with_clipping`` (monotone decreasing in zeta on [0, 0.6]).
    """
    if e >= 1.0:
        return 0.0
    low, high = 0.0, 0.6
    for _ in range(80):
        mid = 0.5 * (low + high)
        if _restitution_with_clipping(mid) > e:
            low = mid
        else:
            high = mid
    return 0.5 * (low + high)
