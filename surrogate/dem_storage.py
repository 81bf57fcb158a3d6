"""The DEM as a storage model: the top rung of the fidelity ladder.

Source: paper section "Digital twin as a distributed particle simulation"
(physics-based micro-tracking in a stockpile: particles fall, impact,
spread; particles at the outlet are removed and reported) and section
"Integration test". The DEM itself is ``surrogate.dem`` (2D disks).

Mapping between the ``ParticleStore`` and the DEM: each pseudo-particle
owned by the storage becomes one DEM disk with the same id; the disk's
diameter follows from the particle's mass and the DEM density (a sphere),
clipped to the configured diameter range. The tracked mass, grade, hardness
and size fractions travel with the disk; the tracking id is the store's
extrinsic attribute ``tracking_id`` when it exists, else the particle id.
After every ``step`` the DEM positions and velocities of the held particles
are written back into the store (x, y; z = 0): the model has geometry
(``has_geometry``), and views show the pile at its disks.

``predict(horizon, rate)`` rule: the feeder takes the held mass in the order
of a *funnel distance* from the nearest outlet centre,
``s = sqrt((dx / funnel_slope)^2 + y^2)`` (funnel flow draws a narrow
column above the outlet first; ``funnel_slope`` = 0.5 by default means a
disk 1 m to the side counts like one 2 m higher). The predicted feed is the
mass ``rate * horizon`` (plus the feeder's current credit) taken in that
order, as in the base class.
"""

from __future__ import annotations

import numpy as np

from cosim.errors import ValidationError
from cosim.storage import StorageModel, budget_shares, check_discharge_rate
from surrogate.dem import Dem, DemConfig


class DemStorage(StorageModel):
    """Stockpile storage model backed by the 2D DEM.

    Parameters
    ----------
    config : DemConfig or dict or str, optional
        DEM configuration (a ``DemConfig``, a dict of its fields, or the path
        of a TOML file); default ``DemConfig()``.
    rng : numpy.random.Generator, optional
        Seeds the DEM's own generator (emission splitting): the DEM's seed is
        drawn from it once (default ``default_rng(0)``).
    inlet : int
        Inlet at which received particles enter (0).
    outlet : int
        Outlet whose feeder ``step`` drives (0).
    funnel_slope : float
        Horizontal weight of the ``predict`` ordering [-] (0.5).
    dem : Dem, optional
        An existing DEM (e.g. from ``Dem.load_checkpoint``) instead of a new one.
    """

    name = "dem"
    has_geometry = True
    checkpointable = True

    def __init__(self, config=None, *, inlet: int = 0, outlet: int = 0,
                 funnel_slope: float = 0.5, dem: Dem | None = None,
                 rng: np.random.Generator | None = None):
        super().__init__(rng=rng)
        if dem is None:
            if isinstance(config, dict):
                config = DemConfig.from_dict(config)
            elif isinstance(config, str):
                config = DemConfig.from_toml(config)
            dem = Dem(config, seed=int(self.rng.integers(2 ** 63)))
        self.dem = dem
        self.inlet = int(inlet)
        self.outlet = int(outlet)
        if not funnel_slope > 0:
            raise ValidationError("funnel_slope", "> 0", f"got {funnel_slope!r}")
        self.funnel_slope = float(funnel_slope)

    def receive(self, ids, t: float) -> None:
        """Emit the store's particles ``ids`` into the DEM at the inlet."""
        ids = np.asarray(ids, dtype=np.uint64).ravel()
        if ids.size == 0:
            return
        slots = self.particles.slots(ids)
        owners = self.particles.owner[slots]
        if (owners != self.owner).any():
            raise ValidationError("ids", f"particles owned by this storage ({self.owner})",
                                  f"{int((owners != self.owner).sum())} owned by others")
        names = self.particles.attribute_names
        tracking = (self.particles.attribute("tracking_id")[slots] if "tracking_id" in names
                    else ids)
        self.dem.emit(self.particles.mass[slots], self.particles.grade[slots],
                      self.particles.hardness[slots], self.particles.f[slots],
                      np.asarray(tracking).astype(np.uint64), inlet=self.inlet, ids=ids)
        self.sync()

    PACKING = 0.82
    """Area fraction of a settled pile of disks [-] (a random close packing in 2D)."""

    def bulk_areal_density(self) -> float:
        """``PACKING`` x the areal density of a disk of the mean diameter: a disk of
        diameter d carries a sphere's mass, rho pi d^3 / 6, on pi d^2 / 4 of area."""
        cfg = self.dem.cfg
        return self.PACKING * cfg.density * 2.0 / 3.0 * cfg.mean_diameter

    @property
    def feeder_credit_kg(self) -> float:
        return float(self.dem.credits[self.outlet])

    def adopt(self, ids, t: float, *, positions=None, credit_kg: float = 0.0) -> None:
        """A hand-over (``StorageModel.adopt``): with positions (in the DEM's
        frame: floor y = 0 centred on x = 0) the disks are dropped to rest in the
        pile's height order (``surrogate.rom.handover.drop_heights``, no deep
        overlaps); without, they are emitted at the inlet. The DEM's clock
        starts at ``t``."""
        from surrogate.rom.handover import drop_heights

        ids = np.asarray(ids, dtype=np.uint64).ravel()
        if positions is None or ids.size == 0:
            self.dem.time = max(self.dem.time, float(t))
            self.receive(ids, t)
        else:
            slots = self.particles.slots(ids)
            mass = self.particles.mass[slots]
            cfg = self.dem.cfg
            half = 0.5 * cfg.floor_width
            at_rest = drop_heights(np.asarray(positions, dtype=np.float64).reshape(-1, 2),
                                   0.5 * cfg.diameter_of_mass(mass), 0.0, -half, half)
            names = self.particles.attribute_names
            tracking = (self.particles.attribute("tracking_id")[slots] if "tracking_id" in names
                        else ids)
            self.dem.time = float(t)
            self.dem.place(at_rest, mass, self.particles.grade[slots],
                           self.particles.hardness[slots], self.particles.f[slots],
                           np.asarray(tracking).astype(np.uint64), ids=ids)
            self.sync()
        self.dem.credits[self.outlet] = float(credit_kg)

    def held_ids(self) -> np.ndarray:
        """Held ids in the predicted order of leaving (funnel distance)."""
        return self.dem.id[self._funnel_order()]

    def held_mass(self) -> float:
        return self.dem.held_mass()

    def step(self, t: float, dt: float, discharge_rate: float) -> np.ndarray:
        """Advance the DEM by ``dt`` [s] with the feeder at ``discharge_rate``
        [kg/s]; return the ids removed by the feeder, in order of removal."""
        self.dem.set_discharge_rate(check_discharge_rate(discharge_rate,
                                                         self.dem.cfg.max_discharge_rate),
                                    outlet=self.outlet)
        self.dem.advance(dt)
        leaving = self.dem.discharged()["id"]
        self.sync()
        return leaving

    def sync(self) -> None:
        """Write DEM positions/velocities of the held particles into the store (z = 0)."""
        if self.particles is None or self.dem.n == 0:
            return
        slots = self.particles.slots(self.dem.id)
        self.particles.position[slots, :2] = self.dem.pos
        self.particles.position[slots, 2] = 0.0
        self.particles.velocity[slots, :2] = self.dem.vel
        self.particles.velocity[slots, 2] = 0.0

    def predict(self, horizon: float, discharge_rate: float):
        """``(ids, mass_kg)`` expected to leave within ``horizon`` [s] (funnel rule)."""
        rate = check_discharge_rate(discharge_rate, self.dem.cfg.max_discharge_rate)
        # the feeder draws no more than its opening passes (Dem.set_discharge_rate)
        rate = min(rate, self.dem.cfg.orifice_capacity())
        order = self._funnel_order()
        return budget_shares(self.dem.id[order], self.dem.mass[order],
                             float(self.dem.credits[self.outlet]) + rate * float(horizon))

    def _funnel_order(self) -> np.ndarray:
        centre = self.dem.cfg.outlets[self.outlet]
        dx = (self.dem.pos[:, 0] - centre) / self.funnel_slope
        return np.argsort(np.hypot(dx, self.dem.pos[:, 1]), kind="stable")
