"""Design of experiments: DEM runs that train and test the ROM.

Source: paper section "Digital twin as a distributed particle simulation"
("run numerous DEM simulations in advance, covering the relevant
state-space [...] using [...] control signals for in- and outflow") and
issue 10: discharge rate, inflow rate and pile state (fill level and shape,
pointy and depleted) are varied; fields are sampled on the ROM grid.

The training stockpile (``training_config``) is a small version of the
paper's pile, so that a design runs in minutes on a laptop core: a 52 m
floor, one inlet 14 m above the centre, one 6 m wide feeder in the floor
below it and rolling resistance 0.2 (with 3-5 m openings and the
default 0.3 the disks arch over the opening and the feeder starves),
disks 0.3-0.5 m (38-177 kg), piles of 70-130 t (800-1500 disks, 7-10 m
tall). The normal stiffness is lowered to 8e6 N/m, which keeps
overlaps below ~1 % of a diameter at the base of this pile (DemConfig's
rule) and allows a larger stable step.

A scenario: from a filled pile (a checkpoint), every ``CONTROL_STEP`` [s]
the inflow q_in * step [kg] of the current lot is emitted at the inlet, the
feeder is set to q_out and the DEM advances; a snapshot per second gives the
mass field M(t) and the displacement velocity field V(t -> t+5 s) on the
grid (``surrogate.rom.grid``, over ``VELOCITY_WINDOW``); the discharge-rate control signal of a
sample is the mass the DEM feeder actually took in that second (an arch
over the opening can starve the feeder below its setpoint). Lots are ``LOT_MASS`` [kg] (about one
truckload, the tracking ids of the accuracy metric) with hardness
alternating 1 and 2 (paper figure "pile_states") and grades drawn
uniformly in [0.2, 0.8].
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cosim.sizes import swebrec
from surrogate.rom.container import Container
from surrogate.rom.dispersion import dispersion_fit
from surrogate.rom.grid import Grid, displacement_velocity_field, mass_field

CONTROL_STEP = 1.0
"""Seconds between control updates, emissions and snapshots [s]."""

LOT_MASS = 15_000.0
"""Mass of one tracked lot [kg] (about one truckload)."""

FILL_RATE = 2000.0
"""Inflow rate [kg/s] while a pile is built."""

SETTLE_TIME = 10.0
"""Seconds a new pile rests before a scenario starts [s]."""


def training_config(**overrides):
    """The DEM configuration of the training stockpile (module docstring)."""
    from surrogate.dem import DemConfig

    values = dict(floor_width=52.0, side_wall_height=1.0, inlets=[[0.0, 14.0]],
                  inlet_width=1.0, outlets=[0.0], outlet_width=6.0, rolling_resistance=0.2,
                  diameter_min=0.3,
                  diameter_max=0.5, normal_stiffness=8.0e6)
    values.update(overrides)
    return DemConfig(**values)


def container_of(cfg, areal_density: float, repose: float) -> Container:
    """The ROM's container for a DEM configuration (inlet 0, outlet 0) with the
    bulk density [kg/m^2] and angle of repose [rad] measured on its piles."""
    half = cfg.floor_width / 2.0
    return Container(x_min=-half, x_max=half, floor=0.0, outlet_x=float(cfg.outlets[0]),
                     inlet_x=float(cfg.inlets[0][0]), areal_density=float(areal_density),
                     repose_angle=float(repose), outlet_width=float(cfg.outlet_width),
                     feeder_zone_height=float(cfg.feeder_zone_height))


def grid_of(cfg, cell_size: float = 1.0, height: float = 12.0) -> Grid:
    """ROM grid over the pile region: the floor width x ``height`` [m]."""
    half = cfg.floor_width / 2.0
    return Grid.covering(-half, half, 0.0, height, cell_size)


BULK_AGE = 4.0
"""Particles younger than this [s] are still falling or spreading (the surface
layer); the bulk fields the ROM learns leave them out."""


def bulk_only(snapshot: dict) -> dict:
    """The snapshot without the particles of the surface layer (``BULK_AGE``)."""
    keep = np.asarray(snapshot["residence_time"]) >= BULK_AGE
    return {k: (v[keep] if np.ndim(v) and len(v) == keep.size else v)
            for k, v in snapshot.items()}


def repose_angle(snapshot: dict, width: float = 1.0) -> float:
    """Angle of repose [rad] of a settled pile: least-squares slope of its
    column heights against |x - x_top| between 15 % and 85 % of the height.

    The ROM container's angle (its sandpile rule), kept as its models were trained
    with it. Both flanks share one line from the highest column, so a flat-topped
    pile reads low: the held-out pile settled at rock stiffness by the explicit DEM
    (a 20 m crest within 0.5 m) gives 21.2 deg here and 30.1 / 29.6 deg flank by
    flank (``surrogate.dem.analysis.side_angles``, the DEM's own read-out, which
    the DEM method comparisons report)."""
    x, y = np.asarray(snapshot["position"]).T
    edges = np.arange(x.min(), x.max() + width, width)
    index = np.digitize(x, edges)
    top = np.full(edges.size + 1, np.nan)
    np.fmax.at(top, index, y + np.asarray(snapshot["radius"]))
    centres = np.append(edges, edges[-1] + width) - 0.5 * width
    ok = np.isfinite(top)
    peak = centres[ok][np.argmax(top[ok])]
    height = np.nanmax(top)
    flank = ok & (top > 0.15 * height) & (top < 0.85 * height)
    slope = -np.polyfit(np.abs(centres[flank] - peak), top[flank], 1)[0]
    return float(np.arctan(slope))


def areal_density(snapshot: dict, grid: Grid) -> float:
    """Settled bulk mass per unit area [kg/m^2]: 90th percentile of full cells."""
    field = mass_field(grid, snapshot["position"], snapshot["mass"]).ravel()
    full = field[field > 0]
    return float(np.percentile(full, 90) / (grid.dx * grid.dy))


@dataclass(frozen=True)
class Scenario:
    """One DEM run of the design.

    Parameters
    ----------
    name : str
    fill : float
        Pile mass at the start [kg].
    discharge_rate, inflow_rate : float
        Feeder and inflow rates [kg/s] (constant over the run).
    duration : float
        Simulated seconds [s].
    """

    name: str
    fill: float
    discharge_rate: float
    inflow_rate: float
    duration: float


class LotFeed:
    """Inflow of lots: tracking id, grade and hardness change every ``LOT_MASS`` kg."""

    def __init__(self, first_tracking_id: int, seed: int):
        self.rng = np.random.default_rng(seed)
        self.tracking_id = int(first_tracking_id) - 1
        self.left = 0.0
        self.grade = self.hardness = 0.0

    def take(self, mass: float):
        """Yield ``(mass, tracking_id, grade, hardness)`` pieces making up ``mass`` [kg]."""
        while mass > 1e-9:
            if self.left <= 1e-9:
                self.tracking_id += 1
                self.left = LOT_MASS
                self.grade = float(self.rng.uniform(0.2, 0.8))
                self.hardness = 1.0 + (self.tracking_id % 2)
            piece = min(mass, self.left)
            self.left -= piece
            mass -= piece
            yield piece, self.tracking_id, self.grade, self.hardness


FEED_F = swebrec(0.1, 1.0, 2.0)
"""Size distribution given to every DEM lot (the default blast curve)."""


def emit_lots(dem, feed: LotFeed, mass: float) -> None:
    """Emit ``mass`` [kg] of the feed's current lot(s) at inlet 0."""
    for piece, tid, grade, hardness in feed.take(mass):
        dem.emit(piece, grade, hardness, FEED_F, tid, inlet=0)


def build_pile(cfg, fill: float, seed: int, progress=None):
    """A DEM pile of ``fill`` kg, built from the inlet and settled; its lots start at id 1."""
    from surrogate.dem import Dem

    dem = Dem(cfg, seed=seed)
    feed = LotFeed(1, seed)
    emitted = 0.0
    while emitted < fill - 1e-9:
        chunk = min(FILL_RATE * CONTROL_STEP, fill - emitted)
        emit_lots(dem, feed, chunk)
        emitted += chunk
        dem.advance(CONTROL_STEP)
        if progress:
            progress(f"building pile: {emitted / 1e3:.0f}/{fill / 1e3:.0f} t")
    dem.advance(SETTLE_TIME + 2.0 * np.sqrt(2.0 * cfg.inlets[0][1] / 9.81))
    return dem, feed


ESCAPE_SPEED_FACTOR = 2.0
"""A disk faster than this multiple of the free-fall speed from the inlet
[-] marks a blown-up run: gravity from the inlet height is the largest
energy source of the stockpile, and a collision with restitution e = 0.3
can at most raise a disk's speed by a factor 1 + e."""

BLOWN_UP_OVERLAP_RATIO = 0.5
"""Overlap over the smaller diameter [-] that marks a blown-up run (the
stable step keeps overlaps near 1-3 % at the base of the training pile)."""


def instability(dem) -> str | None:
    """Why ``dem`` has blown up (an explicit-integration instability of a
    forced time step), or None: a disk outside the container (beyond the
    floor ends or below the floor by more than one largest diameter), a
    disk faster than ``ESCAPE_SPEED_FACTOR`` times the free-fall speed
    sqrt(v_inlet^2 + 2 g h_inlet) [m/s], or an overlap above
    ``BLOWN_UP_OVERLAP_RATIO``. Vectorised over the disks."""
    from surrogate.dem.config import GRAVITY

    if dem.n == 0:
        return None
    cfg = dem.cfg
    margin = cfg.diameter_max
    half = cfg.floor_width / 2.0
    x, y = dem.pos[:, 0], dem.pos[:, 1]
    outside = (np.abs(x) > half + margin) | (y < -margin)
    if outside.any():
        k = int(np.argmax(outside))
        return (f"{int(outside.sum())} disk(s) left the container "
                f"(one at x = {x[k]:.1f} m, y = {y[k]:.1f} m)")
    inlet_height = max(float(h) for _, h in cfg.inlets)
    free_fall = np.sqrt(cfg.inlet_velocity ** 2 + 2.0 * GRAVITY * inlet_height)
    speed = float(np.sqrt((dem.vel ** 2).sum(axis=1)).max())
    if speed > ESCAPE_SPEED_FACTOR * free_fall:
        return (f"disk speed {speed:.3g} m/s above {ESCAPE_SPEED_FACTOR:g} x the free-fall "
                f"speed from the inlet ({free_fall:.3g} m/s)")
    overlap = dem.max_overlap_ratio()
    if overlap > BLOWN_UP_OVERLAP_RATIO:
        return f"overlap {overlap:.2f} of a diameter (limit {BLOWN_UP_OVERLAP_RATIO:g})"
    return None


GUARD_CHECKS_PER_STEP = 4
"""Instability checks (``instability``) per control step of a guarded DEM
run: a blown-up run (forced time step) stops within a quarter second
instead of crawling on with exploding neighbour lists."""


def advance_guarded(dem, seconds: float) -> str | None:
    """Advance ``dem`` by ``seconds`` in ``GUARD_CHECKS_PER_STEP`` chunks;
    return why it blew up, or None. The step count is rounded as
    ``Dem.advance`` rounds it, so a stable run takes exactly the steps of
    ``dem.advance(seconds)`` (checked: bit-identical outflow and fields)."""
    from surrogate.dem.simulation import DemBlowUp

    steps = int(np.ceil(seconds / dem.dt - 1e-9))
    for chunk in np.diff(np.linspace(0, steps, GUARD_CHECKS_PER_STEP + 1).round()):
        try:
            dem.step(int(chunk))
        except DemBlowUp as exc:  # the DEM's own guard, checked every step
            return str(exc)
        reason = instability(dem)
        if reason:
            return reason
    return None


VELOCITY_WINDOW = 5.0
"""Span [s] of the displacements that define a velocity sample (1 s
displacements are dominated by contact rattling and intermittent surface
avalanches; over 5 s the steady funnel flow stands out)."""


def bulk_fields(snapshots: list, grid: Grid):
    """``(time, mass, velocity)`` samples from bulk snapshots one ``CONTROL_STEP`` apart:
    the mass field at t and the displacement velocity over [t, t + VELOCITY_WINDOW]."""
    lag = max(int(round(VELOCITY_WINDOW / CONTROL_STEP)), 1)
    count = max(len(snapshots) - lag, 0)
    times = np.array([float(snapshots[k]["time"]) for k in range(count)])
    masses = np.array([mass_field(grid, snapshots[k]["position"], snapshots[k]["mass"])
                       for k in range(count)]).reshape(count, grid.ny, grid.nx)
    velocities = np.array([displacement_velocity_field(grid, snapshots[k], snapshots[k + lag])
                           for k in range(count)]).reshape(count, grid.ny, grid.nx, 2)
    return times, masses, velocities


def run_scenario(dem, feed: LotFeed, discharge_rate: float, inflow_rate: float,
                 duration: float, grid: Grid, progress=None) -> dict:
    """Run the DEM under constant controls; return the samples and the outflow.

    Returns a dict: ``time`` (S,), ``mass`` (S, ny, nx) [kg], ``velocity``
    (S, ny, nx, 2) [m/s], ``discharge_rate`` (what the feeder took that
    second), ``setpoint``, ``inflow_rate`` (S,) [kg/s],
    ``dispersion_fit`` (S, 2) (``surrogate.rom.dispersion``),
    ``wall_s`` (DEM wall time [s]), ``outflow`` (time, tracking_id, mass,
    grade, hardness per discharged particle).
    """
    start_time = dem.time
    dem.discharged()  # flush: only this run's outflow is returned
    snapshot = dem.snapshot()
    snapshots, taken, records = [bulk_only(snapshot)], [], []
    wall = 0.0
    dem.set_discharge_rate(discharge_rate, outlet=0)
    steps = int(round(duration / CONTROL_STEP))
    for k in range(steps):
        tic = time.perf_counter()
        if inflow_rate > 0:
            emit_lots(dem, feed, inflow_rate * CONTROL_STEP)
        dem.advance(CONTROL_STEP)
        wall += time.perf_counter() - tic
        records.append(dem.discharged())
        taken.append(float(records[-1]["mass"].sum()) / CONTROL_STEP)
        snapshots.append(bulk_only(dem.snapshot()))
        if progress and (k + 1) % 10 == 0:
            progress(f"t = {dem.time - start_time:.0f}/{duration:.0f} s, "
                     f"held {dem.held_mass() / 1e3:.1f} t, wall {wall:.0f} s")
    times, masses, velocities = bulk_fields(snapshots, grid)
    count = len(times)
    lag = len(snapshots) - count
    fits = np.array([dispersion_fit(grid, snapshots[k], snapshots[k + lag])
                     for k in range(count)]).reshape(count, 2)
    taken = np.array(taken[:count])
    outflow = {key: np.concatenate([np.asarray(r[key]) for r in records])
               for key in ("id", "tracking_id", "mass", "grade", "hardness", "time")}
    return {"time": np.array(times), "mass": np.array(masses), "velocity": np.array(velocities),
            "discharge_rate": taken, "setpoint": np.full(count, float(discharge_rate)),
            "inflow_rate": np.full(count, float(inflow_rate)), "dispersion_fit": fits,
            "wall_s": wall,
            "outflow": outflow}


def training_scenarios(quick: bool) -> list[Scenario]:
    """The design: fills x (discharge, inflow) rates up to the paper's 2 t/s,
    60 s each (quick), plus six 120 s runs from a fuller and an emptier pile
    (full design). Pointy piles at the start, depleted ones after draining
    without (or with less) inflow."""
    rows = [(fill, q_out, q_in, 60.0) for fill, q_out, q_in in (
        (110e3, 400.0, 0.0), (110e3, 150.0, 150.0), (110e3, 300.0, 500.0),
        (80e3, 250.0, 0.0), (80e3, 450.0, 450.0), (80e3, 100.0, 300.0),
        (110e3, 2000.0, 1800.0), (80e3, 800.0, 1500.0), (110e3, 1500.0, 700.0))]
    if not quick:
        rows += [(130e3, 100.0, 0.0, 120.0), (130e3, 500.0, 250.0, 120.0),
                 (70e3, 0.0, 400.0, 120.0), (130e3, 300.0, 300.0, 120.0),
                 (130e3, 1800.0, 2000.0, 120.0), (70e3, 1000.0, 1300.0, 120.0)]
    # named by content, so a data directory grown by a later design keeps its runs right
    return [Scenario(f"train_{fill / 1e3:.0f}t_out{q_out:.0f}_in{q_in:.0f}_{duration:.0f}s",
                     fill, q_out, q_in, duration)
            for fill, q_out, q_in, duration in rows]


HELDOUT = Scenario("heldout", fill=95e3, discharge_rate=200.0, inflow_rate=200.0,
                   duration=300.0)
"""Held-out scenario: fill and rates not in the training design, 300 s."""

HELDOUT_SCENARIOS = (
    HELDOUT,
    Scenario("heldout_q1200", fill=100e3, discharge_rate=1200.0, inflow_rate=1200.0,
             duration=300.0),
    Scenario("heldout_q1500", fill=85e3, discharge_rate=1500.0, inflow_rate=1500.0,
             duration=300.0),
)
"""The held-out set: the 200 kg/s run and two at the paper's throughput
(1.2 and 1.5 t/s in and out; paper: up to 2 t/s). Fills and rates are not in
the training design; each scenario's files live in the directory of its name."""


def save_samples(path: Path, result: dict) -> None:
    np.savez_compressed(path, **{k: v for k, v in result.items()
                                 if k not in ("outflow", "wall_s")},
                        wall_s=np.array(result["wall_s"]))


RATE_SMOOTHING = 5.0
"""Window [s] of the moving average applied to the feeder's per-second taken
mass (whole particles of ~100 kg make the raw per-second rate jumpy)."""


def _smoothed(rate: np.ndarray) -> np.ndarray:
    width = max(int(round(RATE_SMOOTHING / CONTROL_STEP)), 1)
    padded = np.pad(rate, (width // 2, width - 1 - width // 2), mode="edge")
    return np.convolve(padded, np.ones(width) / width, mode="valid")


def load_samples(directory) -> dict:
    """Concatenate every ``train/*.npz`` sample file under ``directory``
    (discharge rates smoothed over ``RATE_SMOOTHING`` seconds per run);
    ``run`` (S,) numbers the file each sample came from."""
    files = sorted(Path(directory, "train").glob("*.npz"))
    parts = [dict(np.load(f)) for f in files]
    for part in parts:
        part["discharge_rate"] = _smoothed(part["discharge_rate"])
    if not parts:
        from cosim.errors import ValidationError

        raise ValidationError("data", "a DOE directory with train/*.npz sample files",
                              f"none under {directory}")
    samples = {key: np.concatenate([p[key] for p in parts])
               for key in ("time", "mass", "velocity", "discharge_rate", "inflow_rate")}
    samples["run"] = np.concatenate([np.full(len(p["time"]), k) for k, p in enumerate(parts)])
    if all("dispersion_fit" in p for p in parts):  # files from before the dispersion have none
        samples["dispersion_fit"] = np.concatenate([p["dispersion_fit"] for p in parts])
    return samples


def grid_and_container(directory) -> tuple[Grid, Container]:
    """The grid and the container of a design folder (``read_meta``)."""
    meta = read_meta(directory)
    return Grid.from_dict(meta["grid"]), Container.from_dict(meta["container"])


def training_runs(directory) -> tuple[Grid, Container, dict, list[str]]:
    """``(grid, container, samples, run names)`` of a design folder:
    ``grid_and_container``, ``load_samples``, and each run's name
    (``samples["run"]`` k is the k-th name)."""
    grid, container = grid_and_container(directory)
    names = [f.stem for f in sorted(Path(directory, "train").glob("*.npz"))]
    return grid, container, load_samples(directory), names


def write_meta(directory: Path, cfg, grid: Grid, container: Container, extra: dict) -> None:
    meta = {"dem_config": cfg.to_dict(), "grid": grid.to_dict(),
            "container": container.to_dict(), **extra}
    Path(directory, "doe.json").write_text(json.dumps(meta, indent=1))


def read_meta(directory) -> dict:
    path = Path(directory, "doe.json")
    if not path.is_file():
        from cosim.errors import ValidationError

        raise ValidationError("data", "a DOE directory holding doe.json (minetwin rom evaluate "
                              "--quick writes one)", f"no {path}")
    return json.loads(path.read_text())
