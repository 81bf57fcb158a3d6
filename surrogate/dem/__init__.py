"""2D soft-disk DEM of the stockpile (numba): pile formation and feeder discharge.

Stable public API (used by the ROM, ``surrogate/rom``, and ``DemStorage``)::

    from surrogate.dem import DemConfig, Dem
    cfg = DemConfig(...)                 # dataclass, SI units, defaults documented;
                                         # DemConfig.from_toml(path) / .from_dict(d) / .to_dict()
    dem = Dem(cfg, seed=0)               # optional dt=..., force=True for dt > stable_dt;
                                         # DemConfig(method="nonsmooth"): the time-implicit
                                         # DEM (nonsmooth.py), default dt 11 ms, no limit
    # a run that blows up raises DemBlowUp (what was seen, time, step, cause)
    ids = dem.emit(mass_kg, grade, hardness, f16, tracking_id, inlet=0, ids=None)
        # ids=None: mass_kg is one lot, split into pseudo-particles with new ids;
        # ids given: one disk per id, mass_kg per id. Returns uint64 ids.
    dem.set_discharge_rate(rate_kg_s, outlet=0)   # 0..cfg.max_discharge_rate (2000) kg/s;
        # returns the rate drawn: capped at what the opening passes (Beverloo,
        # cfg.orifice_capacity()), with a FeederCapped warning; dem.feeder_state()
    dem.advance(seconds)   /  dem.step(n_steps)   # feeders remove disks at the outlets
    dem.discharged()       # dict of arrays since the last call: id, tracking_id, mass,
                           # grade, hardness, f (M,16), entry_time, time (removal), outlet
    dem.snapshot()         # dict: time, id, tracking_id, position (N,2), velocity (N,2),
                           # omega, radius, mass, grade, hardness, f, entry_time, residence_time
    dem.save_checkpoint(path); Dem.load_checkpoint(path)   # continues bit-for-bit
    dem.dt, dem.stable_dt, dem.time, dem.held_mass(), dem.n, dem.energy()

Conventions: 2D, gravity along -y, floor at y = 0 centred on x = 0; positions
are (N, 2) inside the DEM (a ParticleStore uses (N, 3) with z = 0). ``mass``
is the tracked ore mass of a pseudo-particle (what the feeder and the mass
balance count); the disk's dynamic mass is that of a sphere of its diameter.
Snapshot files for ROM training: ``surrogate.dem.snapshots``.
"""

from surrogate.dem.config import DemConfig
from surrogate.dem.simulation import Dem, DemBlowUp, FeederCapped

__all__ = ["Dem", "DemBlowUp", "DemConfig", "FeederCapped"]
