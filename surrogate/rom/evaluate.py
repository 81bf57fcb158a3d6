"""Build the design, train, and score every storage model on the held-out run.

Source: issue 10 "What it must show": a held-out scenario (rates and pile
state not in the training set) run for >= 300 s from the same initial state
with the same inflow and discharge control by the DEM, a second DEM whose
initial positions differ by 1e-6 m (the noise floor), FIFO, perfect mixing
and the ROM; tracking error, velocity-field error, outflow grade/hardness
errors and wall time per simulated second (``surrogate.rom.metrics``).

Data directory layout (written by ``build_data``)::

    doe.json                 DEM config, grid, container, scenarios
    piles/fill_<kg>.npz      DEM checkpoints of settled piles
    train/<scenario>.npz     samples: time, mass, velocity, rates
    <heldout>/initial.npz    DEM checkpoint a held-out scenario starts from
    <heldout>/emissions.npz  every particle the inlet receives: time, id, mass, ...
    <heldout>/dem.npz        reference DEM: outflow, fields per second, wall time
    <heldout>/dem_perturbed.npz  the same with positions moved by 1e-6 m
    <heldout>/dem_replica<k>.npz further replicas, moved by 1e-6 m in other
                             directions (``DEM_REPLICAS`` runs in all)
    <heldout>/dem_dt<f>.npz  the DEM at f x its stable step (speed-vs-accuracy
                             chart; a blown-up run: ``unstable``, when, why)

with one ``<heldout>`` directory per scenario of ``doe.HELDOUT_SCENARIOS``
(``heldout`` is the 200 kg/s one; ``heldout_q1200``, ``heldout_q1500`` run at
the paper's throughput). The summary has each scenario's scores under
``scenarios`` and their aggregate at the top level (``AGGREGATE_NOTE``).
"""

from __future__ import annotations

import copy
import time
import warnings
from dataclasses import asdict
from functools import partial
from pathlib import Path

import numpy as np

from cosim import batch
from cosim.errors import ValidationError, check_finite_range
from cosim.particles import ParticleStore
from cosim.storage import make_storage
from surrogate.rom import doe, metrics, rest
from surrogate.rom.dispersion import dispersivity
from surrogate.rom.grid import Grid, mean_field
from surrogate.rom.hanging import HANGING_LIMIT, hanging_share, hanging_share_of
from surrogate.rom.model import (FLUX_FLOOR, FLUX_FLOORS, RomModel, flux_samples, pod_basis,
                                  pod_residual)
from surrogate.rom.packing import settled_density
from surrogate.rom.provenance import training_provenance
from surrogate.rom.registration import register

PERTURBATION = 1e-6
"""Initial-position perturbation [m] of the noise-floor DEM runs."""

DEM_REPLICAS = 3
"""DEM runs per held-out scenario: the reference and replicas whose initial positions
differ by ``PERTURBATION``. The DEM is chaotic, so one run is one realisation: every
model is scored against each replica (mean and spread), and the noise floor is the
error between replicas (every pair)."""

OWNER = 1
OUTFLOW_KEYS = ("time", "tracking_id", "mass", "grade", "hardness")


def _say(progress, message):
    if progress:
        progress(message)


# ----------------------------------------------------------------- data
def _build_pile_file(cfg, fill: float, seed: int, path: Path, progress) -> None:
    _say(progress, f"DEM: building a {fill / 1e3:.0f} t pile")
    dem, _ = doe.build_pile(cfg, fill, seed)
    dem.save_checkpoint(path)


def _run_training(directory: Path, scenario, first_tracking_id: int, seed: int, grid: Grid,
                  progress) -> None:
    from surrogate.dem import Dem

    s = scenario
    _say(progress, f"DEM: {s.name} (fill {s.fill / 1e3:.0f} t, q_out {s.discharge_rate:g}"
                   f" kg/s, q_in {s.inflow_rate:g} kg/s, {s.duration:g} s)")
    dem = Dem.load_checkpoint(directory / "piles" / f"fill_{s.fill:.0f}.npz")
    result = doe.run_scenario(dem, doe.LotFeed(first_tracking_id, seed), s.discharge_rate,
                              s.inflow_rate, s.duration, grid)
    doe.save_samples(directory / "train" / f"{s.name}.npz", result)


def build_data(directory, quick: bool = True, seed: int = 0, progress=None,
               reference_dt_factors=(), workers: int = 2,
               dt_ladder_scenarios=(doe.HELDOUT.name,), executor=None,
               method_runs=()) -> Path:
    """Run the DOE and the held-out DEM runs into ``directory``; runs already
    on disk are kept. Independent DEM runs go to ``executor`` (``cosim.batch``;
    default: ``workers`` local processes). The held-out scenarios named in
    ``dt_ladder_scenarios`` also run the DEM at
    ``reference_dt_factors`` times its stable step (``dem_dt<factor>.npz``;
    forced steps, stopped and marked when they blow up), and once per
    ``(name, changes)`` of ``method_runs`` with those ``DemConfig`` changes from
    the same start (``<name>.npz``; e.g. the nonsmooth method)."""
    from surrogate.dem import Dem

    if executor is None:
        with batch.LocalExecutor(workers) as executor:
            return build_data(directory, quick, seed, progress, reference_dt_factors,
                              dt_ladder_scenarios=dt_ladder_scenarios, executor=executor,
                              method_runs=method_runs)
    directory = Path(directory)
    if (directory / "doe.json").is_file() and doe.read_meta(directory).get("quick") and not quick:
        _say(progress, f"{directory} holds the quick design: growing it to the full design "
                       "(runs on disk are kept; pass --quick to stay with the quick one)")
    for sub in ("piles", "train"):
        (directory / sub).mkdir(parents=True, exist_ok=True)
    cfg = doe.training_config()
    grid = doe.grid_of(cfg)
    scenarios = doe.training_scenarios(quick)
    # pile seeds: the training fills and the 200 kg/s held-out fill keep the
    # seeds they had before the paper-throughput scenarios were added
    first = sorted({s.fill for s in scenarios} | {doe.HELDOUT.fill})
    fills = first + sorted({s.fill for s in doe.HELDOUT_SCENARIOS} - set(first))
    piles = {fill: directory / "piles" / f"fill_{fill:.0f}.npz" for fill in fills}
    batch.run_calls([(_build_pile_file, {"cfg": cfg, "fill": fill, "seed": seed + k,
                                         "path": piles[fill], "progress": progress})
                     for k, fill in enumerate(fills) if not piles[fill].exists()], executor)
    container = doe.container_of(cfg, *training_pile_properties(
        [piles[fill] for fill in sorted({s.fill for s in scenarios})], grid))
    doe.write_meta(directory, cfg, grid, container,
                   {"quick": quick, "seed": seed,
                    "scenarios": [asdict(s) for s in scenarios],
                    "heldout": asdict(doe.HELDOUT),
                    "heldout_scenarios": [asdict(s) for s in doe.HELDOUT_SCENARIOS]})
    jobs = [(_run_training, {"directory": directory, "scenario": s,
                             "first_tracking_id": 1000 + 100 * k, "seed": seed, "grid": grid,
                             "progress": progress})
            for k, s in enumerate(scenarios)
            if not (directory / "train" / f"{s.name}.npz").exists()]
    for k, scenario in enumerate(doe.HELDOUT_SCENARIOS):
        heldout = directory / scenario.name
        heldout.mkdir(parents=True, exist_ok=True)
        initial = heldout / "initial.npz"
        if not initial.exists():
            Dem.load_checkpoint(piles[scenario.fill]).save_checkpoint(initial)
        if not (heldout / "emissions.npz").exists():
            _write_emissions(heldout, Dem.load_checkpoint(initial), scenario, seed + 100 * k)
        runs = [(name, PERTURBATION if k else 0.0, 1.0, None)
                for k, name in enumerate(replica_names(DEM_REPLICAS))]
        if scenario.name in dt_ladder_scenarios:  # the speed-vs-accuracy chart's DEM ladder
            runs += [(f"dem_dt{f:g}", 0.0, f, None) for f in reference_dt_factors]
            runs += [(name, 0.0, 1.0, dict(changes)) for name, changes in method_runs]
        jobs += [(_run_heldout_dem, {"heldout": heldout, "name": name, "grid": grid,
                                     "perturbation": perturb, "dt_factor": factor,
                                     "seed": seed, "progress": progress, "changes": changes})
                 for name, perturb, factor, changes in runs
                 if not (heldout / f"{name}.npz").exists()]
    batch.run_calls(jobs, executor)  # the results are files: order plays no part
    return directory


def training_pile_properties(pile_files, grid: Grid) -> tuple[float, float]:
    """(bulk areal density [kg/m^2], angle of repose [rad]) of the container:
    medians over the settled piles the training scenarios start from (the
    held-out piles play no part in the model)."""
    from surrogate.dem import Dem

    piles = [Dem.load_checkpoint(path).snapshot() for path in pile_files]
    return (float(np.median([doe.areal_density(pile, grid) for pile in piles])),
            float(np.median([doe.repose_angle(pile) for pile in piles])))


def _write_emissions(heldout: Path, dem, scenario, seed: int) -> None:
    """The held-out inflow, particle by particle, so every model gets the same particles."""
    from surrogate.dem.emitter import split_lot

    rng = np.random.default_rng(seed + 7)
    feed = doe.LotFeed(500, seed + 7)
    rows = {k: [] for k in ("time", "id", "mass", "tracking_id", "grade", "hardness")}
    next_id = dem.next_id
    steps = int(round(scenario.duration / doe.CONTROL_STEP))
    for k in range(steps):
        for piece, tid, grade, hardness in feed.take(scenario.inflow_rate * doe.CONTROL_STEP):
            masses = split_lot(dem.cfg, piece, rng)
            count = masses.size
            rows["time"].append(np.full(count, dem.time + k * doe.CONTROL_STEP))
            rows["id"].append(np.arange(next_id, next_id + count, dtype=np.uint64))
            rows["mass"].append(masses)
            rows["tracking_id"].append(np.full(count, tid, dtype=np.uint64))
            rows["grade"].append(np.full(count, grade))
            rows["hardness"].append(np.full(count, hardness))
            next_id += count
    np.savez_compressed(heldout / "emissions.npz",
                        **{k: np.concatenate(v) for k, v in rows.items()},
                        discharge_rate=np.array(scenario.discharge_rate),
                        duration=np.array(scenario.duration))


def _emission_batches(emissions: dict, t0: float, steps: int):
    step_index = np.round((emissions["time"] - t0) / doe.CONTROL_STEP).astype(np.int64)
    bounds = np.searchsorted(step_index, np.arange(steps + 1))
    return [slice(bounds[k], bounds[k + 1]) for k in range(steps)]


def _run_heldout_dem(heldout: Path, name: str, grid: Grid, perturbation: float,
                     dt_factor: float, seed: int, progress, changes: dict | None = None) -> None:
    """One DEM run of the held-out scenario into ``heldout/<name>.npz``, with the
    ``DemConfig`` ``changes`` if any (e.g. ``{"method": "nonsmooth"}``). A run
    that blows up (``doe.instability``) stops there and is saved with
    ``unstable`` = 1, ``unstable_at`` [s after t0], ``unstable_reason``, its
    outflow and wall time so far (no fields)."""
    from surrogate.dem import Dem

    _say(progress, f"DEM: held-out run {heldout.name}/{name}")
    dem = Dem.load_checkpoint(heldout / "initial.npz", changes or None)
    if dt_factor != 1.0:
        dem.set_dt(dem.stable_dt * dt_factor, force=True)
    if perturbation:  # each replica moved in directions of its own
        names = replica_names(DEM_REPLICAS)
        replica = names.index(name) if name in names else 1
        angle = np.random.default_rng(seed + 11 + 1000 * (replica - 1)).uniform(
            0, 2 * np.pi, dem.n)
        dem.pos = dem.pos + perturbation * np.column_stack((np.cos(angle), np.sin(angle)))
    emissions = dict(np.load(heldout / "emissions.npz"))
    steps = int(round(float(emissions["duration"]) / doe.CONTROL_STEP))
    batches = _emission_batches(emissions, dem.time, steps)
    dem.set_discharge_rate(float(emissions["discharge_rate"]))
    dem.discharged()
    snapshots = [dem.snapshot()]
    t0 = float(snapshots[0]["time"])
    wall, unstable = 0.0, None
    for k, rows in enumerate(batches):
        tic = time.perf_counter()
        if rows.stop > rows.start:
            dem.emit(emissions["mass"][rows], emissions["grade"][rows],
                     emissions["hardness"][rows], doe.FEED_F, emissions["tracking_id"][rows],
                     inlet=0, ids=emissions["id"][rows])
        unstable = doe.advance_guarded(dem, doe.CONTROL_STEP)  # the guard's cost counts too
        wall += time.perf_counter() - tic
        if unstable:
            _say(progress, f"  {heldout.name}/{name}: unstable at t = {dem.time - t0:.2f} s "
                           f"({unstable}); stopped")
            break
        snapshots.append(dem.snapshot())
        if (k + 1) % 30 == 0:
            _say(progress, f"  {heldout.name}/{name}: t = {k + 1}/{steps} s, wall {wall:.0f} s")
    out = dem.discharged()
    common = {**{f"out_{k}": np.asarray(out[k]) for k in OUTFLOW_KEYS},
              "wall_s": np.array(wall), "dt": np.array(dem.dt), "steps": np.array(steps),
              "particles": np.array(len(snapshots[0]["id"])), "t0": np.array(t0),
              "discharge_rate": emissions["discharge_rate"]}
    if unstable:
        np.savez_compressed(heldout / f"{name}.npz", **common, unstable=np.array(1),
                            unstable_at=np.array(dem.time - t0),
                            unstable_reason=np.array(unstable))
        return
    bulk = [doe.bulk_only(s) for s in snapshots]
    times, masses, velocities = doe.bulk_fields(bulk, grid)
    fields = {"time": times, "mass": masses, "velocity": velocities,
              "grade": [mean_field(grid, s["position"], s["mass"], s["grade"])
                        for s in bulk[:len(times)]],
              "hardness": [mean_field(grid, s["position"], s["mass"], s["hardness"])
                           for s in bulk[:len(times)]]}
    np.savez_compressed(heldout / f"{name}.npz", **common, unstable=np.array(0),
                        **{f"field_{k}": np.array(v) for k, v in fields.items()})


def replica_names(count: int) -> list[str]:
    """The DEM runs of a held-out scenario: the reference ``dem``, then
    ``dem_perturbed`` and ``dem_replica<k>`` (files ``<name>.npz``)."""
    return ["dem", "dem_perturbed", *(f"dem_replica{k}" for k in range(2, count))][:count]


def stable_replicas(heldout: Path) -> list[dict]:
    """The held-out scenario's DEM replicas on disk that did not blow up, in order."""
    runs = [load_run(heldout / f"{name}.npz") for name in replica_names(DEM_REPLICAS)
            if (heldout / f"{name}.npz").is_file()]
    return [run for run in runs if not int(run.get("unstable", 0))]


def spread(values: list[float]) -> dict:
    """Mean, min, max, standard deviation (ddof 1; 0 for one value) and count."""
    values = np.asarray(values, dtype=np.float64)
    return {"mean": float(values.mean()), "min": float(values.min()),
            "max": float(values.max()),
            "std": float(values.std(ddof=1)) if values.size > 1 else 0.0,
            "n": int(values.size)}


def ensemble_score(outflow: dict, references: list[dict], t0: float, t1: float,
                   window: float = metrics.WINDOW_S) -> dict:
    """``score`` against each DEM replica: the mean of each error, the tracking
    errors replica by replica (``tracking_errors``) and their spread (mean, min,
    max, std, n)."""
    scores = [score(outflow, reference, t0, t1, window) for reference in references]
    out = {key: float(np.mean([s[key] for s in scores]))
           for key in ("tracking_error", "grade_error", "hardness_error")}
    out["tracking_errors"] = [float(s["tracking_error"]) for s in scores]
    out["tracking_error_spread"] = spread([s["tracking_error"] for s in scores])
    return out


def noise_floor(references: list[dict], t0: float, t1: float, window: float = metrics.WINDOW_S) -> dict:
    """The errors between the DEM replicas, every pair once (``ensemble_score``'s keys)."""
    if len(references) < 2:
        raise ValidationError("references", "at least 2 DEM replicas",
                              f"got {len(references)}")
    pairs = [score(references[j], references[i], t0, t1, window)
             for i in range(len(references)) for j in range(i + 1, len(references))]
    out = {key: float(np.mean([p[key] for p in pairs]))
           for key in ("tracking_error", "grade_error", "hardness_error")}
    out["tracking_error_spread"] = spread([p["tracking_error"] for p in pairs])
    return out


def scenario_duration(heldout: Path) -> float:
    """Simulated seconds [s] of the held-out scenario."""
    with np.load(Path(heldout) / "emissions.npz") as data:
        return float(data["duration"])


def load_run(path) -> dict:
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def outflow_of(run: dict) -> dict:
    return {k: run[f"out_{k}"] for k in OUTFLOW_KEYS}


# -------------------------------------------------------------- training
MODEL_CANDIDATES = [(modes, velocity_modes, ridge)
                    for modes, velocity_modes in ((2, 2), (4, 4), (8, 8), (12, 16))
                    for ridge in (1e-1, 1.0, 10.0, 100.0)]
"""(mass modes, velocity modes, ridge) tried by ``train``'s model selection."""

REGISTERED_CANDIDATES = [(modes, velocity_modes, ridge) for modes in (2, 4, 8)
                         for velocity_modes in (4, 8, 16, 32)
                         for ridge in (1.0, 10.0, 100.0, 1000.0)]
"""The candidates of a registered fit (``registration="height"``): up to 32
velocity modes, as the registered fields spread over more modes than the fixed
grid's (surrogate/rom/README.md, "A registered fit")."""


def _fit(grid, container, samples, keep, modes, velocity_modes, ridge,
         bases=None, target: str = "velocity", flux_floor: float = FLUX_FLOOR,
         fill_law: str | None = None, registration: tuple = (None, None)) -> RomModel:
    return RomModel(grid, modes, velocity_modes, ridge, container, target=target,
                    flux_floor=flux_floor, fill_law=fill_law, registration=registration[0],
                    registration_density=registration[1]).fit(
        samples["mass"][keep], samples["discharge_rate"][keep], samples["inflow_rate"][keep],
        samples["velocity"][keep], bases=bases)


def fitted_bases(grid, samples, keep, registration: tuple = (None, None),
                 target: str = "velocity") -> tuple:
    """The POD bases (``pod_basis``) a ``RomModel`` fitted on the samples ``keep``
    uses: the mass fields' and the uncentred one of the fitted field (the
    velocity, or with ``target="flux"`` the flux, registered with a
    ``registration`` ``(registration, registration_density)``), so that a fold's
    or a design's SVDs are done once for all candidates."""
    fitted = samples["velocity"][keep]
    if target == "flux":
        fitted = flux_samples(samples["mass"][keep], fitted)
    if registration[0] is not None:
        fitted = register(fitted, samples["mass"][keep], grid,
                          registration[1]).reshape(len(fitted), -1)
    return pod_basis(samples["mass"][keep]), pod_basis(fitted, centred=False)


def leave_one_run_out_errors(grid, samples, candidates, target: str = "velocity",
                             container=None, floors=None, fill_law: str | None = None,
                             registration: tuple = (None, None)) -> dict:
    """Each candidate ``(modes, velocity modes, ridge)``'s mean velocity-field
    relative error on each training run when the model is fitted on the other
    runs (cross-validation by whole DEM runs). The SVDs of a fold are done once
    for all candidates. With ``target="flux"`` (``container`` needed) the keys are
    ``(modes, velocity modes, ridge, flux_floor)`` over ``floors`` (default
    ``FLUX_FLOORS``), the error that of the model's velocity (its flux over the
    held run's DEM cell mass, floored) against the DEM's, the same metric;
    ``fill_law`` as ``RomModel``'s (fitted on the fold's runs); ``registration``
    ``(registration, registration_density)`` as ``RomModel``'s (the error is that
    of the field mapped back on the grid)."""
    floors = (FLUX_FLOORS if floors is None else tuple(floors)) if target == "flux" else (None,)
    keys = [c if target == "velocity" else (*c, f) for c in candidates for f in floors]
    errors = {key: [] for key in keys}
    for run in np.unique(samples["run"]):
        held = samples["run"] == run
        bases = fitted_bases(grid, samples, ~held, registration, target)
        for candidate in candidates:
            model = _fit(grid, container, samples, ~held, *candidate, bases=bases,
                         target=target, fill_law=fill_law, registration=registration)
            for floor in floors:
                if floor is not None:
                    model.flux_floor = floor
                predicted = np.array([model.predict(m, q, i, check=False) for m, q, i in
                                      zip(samples["mass"][held], samples["discharge_rate"][held],
                                          samples["inflow_rate"][held])])
                key = candidate if floor is None else (*candidate, floor)
                errors[key].append(metrics.velocity_field_rel_error(
                    predicted, samples["velocity"][held], samples["mass"][held]))
    return {key: float(np.mean(e)) for key, e in errors.items()}


def leave_one_run_out_residual(samples, n_mass_modes: int) -> float:
    """The largest ``mass_distribution_residual`` of a training run's states under
    the mass modes of the other runs: how far from the basis a pile lies that
    the model has not seen. A new pile of the same making differs from every
    training state by its particles (about 30 disks per cell), which the
    training states' own residuals do not allow for."""
    worst = 0.0
    for run in np.unique(samples["run"]):
        held = samples["run"] == run
        basis = pod_basis(samples["mass"][~held])
        worst = max(worst, float(pod_residual(basis, n_mass_modes, samples["mass"][held]).max()))
    return worst


def _training_pile(grid: Grid, mass_field_kg: np.ndarray, pool: np.ndarray,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Particles (masses drawn from ``pool`` [kg], positions uniform within their
    cell [m]) that fill the cells of a sampled mass field ``(ny, nx)`` [kg] in order."""
    cells = np.asarray(mass_field_kg, dtype=np.float64).ravel()
    total = float(cells.sum())
    count = int(total / pool.mean() * 1.2) + 16
    mass = rng.choice(pool, count)
    while mass.sum() < total:
        mass = np.concatenate((mass, rng.choice(pool, count)))
    centre = np.cumsum(mass) - 0.5 * mass  # each particle goes to the cell its mass centre falls in
    keep = centre < total
    mass, centre = mass[keep], centre[keep]
    cell = np.minimum(np.searchsorted(np.cumsum(cells), centre, side="right"), cells.size - 1)
    row, column = np.divmod(cell, grid.nx)
    position = np.stack([grid.x_min + (column + rng.random(cell.size)) * grid.dx,
                         grid.y_min + (row + rng.random(cell.size)) * grid.dy], axis=1)
    return mass, position


def rom_numerical_dispersivity(model: RomModel, directory, samples: dict,
                               seed: int = 0) -> float | None:
    """The dispersivity [m] the ROM shows without its random walk (``None`` when
    the training files hold no discharged particles' masses).

    The ROM's own scheme already scatters particles about the mean flow: the
    column re-packing (``surface.settle``) moves a particle up or down by the
    mass of every particle that enters or leaves the column below it, the
    avalanches and the feeder move single particles (on the paper design the
    avalanches dominate: surrogate/rom/README.md). Measured as
    ``dispersion.dispersion_fit`` measures the DEM (pairs of bulk snapshots
    ``doe.VELOCITY_WINDOW`` apart, one per ``doe.CONTROL_STEP``), on every
    training run: the ROM (``model`` with dispersivity 0, ``RomStorage``'s
    default surface layer, transport and packing, generator seeded ``seed``) starts from the run's first sampled mass
    field (particles drawn from the masses the run's DEM discharged,
    ``_training_pile``), is driven at the run's commanded discharge rate and
    mean inflow rate for as many seconds as the run was sampled, and its fits are
    pooled as ``dispersion.dispersivity`` pools the DEM's. Training data only:
    no held-out scene enters."""
    from surrogate.rom.dispersion import dispersion_fit
    from surrogate.rom.storage import RomStorage

    files = sorted(Path(directory, "train").glob("*.npz"))  # doe.load_samples' run order
    pools, setpoints = [], []
    for path in files:
        with np.load(path) as data:
            if "out_mass" not in data.files or "setpoint" not in data.files:
                return None
            pools.append(np.asarray(data["out_mass"], dtype=np.float64))
            setpoints.append(float(data["setpoint"][0]))
    pool = np.concatenate(pools)
    if pool.size == 0:
        return None
    bare = copy.copy(model)  # the same fitted arrays, without the random walk
    bare.dispersivity = 0.0
    rng = np.random.default_rng(seed)
    lag = max(int(round(doe.VELOCITY_WINDOW / doe.CONTROL_STEP)), 1)
    fits = []
    for run in np.unique(samples["run"]):
        rows = np.flatnonzero(samples["run"] == run)
        steps = rows.size + lag
        discharge = setpoints[run]  # the rate the DEM's feeder was commanded
        inflow = float(samples["inflow_rate"][rows].mean())
        mass, position = _training_pile(model.grid, samples["mass"][rows[0]], pool, rng)
        # the inflow: particles drawn from the pool, each arriving in the step in
        # which the fed mass passes its own
        fed = rng.choice(pool, int(inflow * steps * doe.CONTROL_STEP / pool.min()) + 1)
        arrival = np.searchsorted(np.cumsum(fed), inflow * doe.CONTROL_STEP
                                  * np.arange(1, steps + 1), side="right")
        store = ParticleStore(capacity=4096)
        ids = store.add(mass=mass, f=doe.FEED_F, grade=np.full(mass.size, 0.01),
                        hardness=np.ones(mass.size), owner=OWNER, time=0.0)
        storage = RomStorage(bare, rng=np.random.default_rng(int(rng.integers(2 ** 31))))
        storage.bind(store, OWNER)
        storage.place(ids, position)

        snapshots, first = [storage.bulk_snapshot(0.0)], 0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a drawn pile may sit just outside the ranges
            for k in range(steps):
                t = k * doe.CONTROL_STEP
                if arrival[k] > first:
                    count = arrival[k] - first
                    new = store.add(mass=fed[first:arrival[k]], f=doe.FEED_F,
                                    grade=np.full(count, 0.01), hardness=np.ones(count),
                                    owner=OWNER, time=t)
                    storage.receive(new, t)
                    first = arrival[k]
                leaving = storage.step(t, doe.CONTROL_STEP, discharge)
                store.remove_slots(store.slots(leaving))
                snapshots.append(storage.bulk_snapshot(t + doe.CONTROL_STEP))
        fits += [dispersion_fit(model.grid, snapshots[k], snapshots[k + lag])
                 for k in range(len(snapshots) - lag)]
    return dispersivity(fits)


def _completed(model: RomModel, directory, samples: dict, dem_config: dict | None,
               record: dict, rest_fraction: float | None, storage_options: dict,
               progress=None, residuals: dict | None = None,
               walk: float | None = None) -> RomModel:
    """``model`` (fitted) as ``train`` ships it: its ``storage_settings``, its
    ``validation`` (``record``, then the residual's training range: the larger of
    the training states' own and ``leave_one_run_out_residual``, kept in
    ``residuals`` by mass modes when given), the design's DEM ``dem_config``,
    then the random walk's dispersivity (what the ROM's own scheme under those
    settings leaves short of the DEM's dispersion, unless ``walk`` [m] is given)
    and the resting bulk's share (fitted unless ``rest_fraction`` is given)."""
    model.storage_settings = dict(storage_options)
    model.validation = dict(record)
    if np.unique(samples["run"]).size > 1:
        seen = model.ranges["mass_distribution_residual"][1]
        residuals = {} if residuals is None else residuals
        if model.n_mass_modes not in residuals:
            residuals[model.n_mass_modes] = leave_one_run_out_residual(samples,
                                                                       model.n_mass_modes)
        unseen = residuals[model.n_mass_modes]
        model.ranges["mass_distribution_residual"] = [0.0, max(seen, unseen)]
        model.validation["mass_distribution_residual_max"] = {"training_states": seen,
                                                              "unseen_runs": unseen}
    model.dem_config = dem_config
    if walk is not None:
        model.dispersivity = walk
        model.validation["dispersivity"] = {"applied": walk, "given": True}
    elif "dispersion_fit" in samples:
        measured = dispersivity(samples["dispersion_fit"])
        own = rom_numerical_dispersivity(model, directory, samples)
        # independent random walks add their diffusivities: the walk adds only
        # what the ROM's own scheme leaves short of the DEM's dispersion
        model.dispersivity = measured if own is None else max(measured - own, 0.0)
        model.validation["dispersivity"] = {"dem": measured, "rom_without_walk": own,
                                            "applied": model.dispersivity}
        _say(progress, f"bulk dispersivity {measured:.4f} m measured on the DEM runs, "
                       + ("" if own is None else f"{own:.4f} m shown by the ROM without its "
                          "random walk, ") + f"{model.dispersivity:.4f} m applied")
    if rest_fraction is None:
        fitted = rest.fit_samples(samples, model)
        model.rest_fraction = fitted["best"]
        model.validation["rest"] = fitted
        _say(progress, "resting bulk: " + (
            f"cells slower than {model.rest_fraction:g} of the feeder's mean outlet speed "
            f"rest (Youden's index {max(fitted['youden']):.3f})" if model.rest_fraction
            else "off (a point outlet, no discharging sample or no share that tells "
                 "resting from moving cells)"))
    else:
        model.rest_fraction = rest_fraction
    return model


VALIDATION_ROM_SEEDS = 2
"""Default ROM seeds per validation scene of ``train``'s selection by tracking."""

SELECT_BY = ("mean", "floor-excess")
"""What ``train``'s selection by tracking minimises: the mean tracking error over the
validation scenes, or the largest excess of a scene's over its DEM noise floor
(``surrogate.rom.validation``)."""

STORAGE_SETTINGS = ("packing", "packing_density", "landing_spread", "void_gap")
"""The ``RomStorage`` options a model chosen by tracking keeps (``RomModel.storage_settings``)."""


def _candidate_name(key: tuple) -> str:
    """A candidate's options as its record names them: modes/modes/ridge (``4/16/10``)."""
    return "/".join(f"{x:g}" for x in key)


def check_storage_options(options: dict | None) -> dict:
    """``options`` (``STORAGE_SETTINGS`` only, None values dropped) as ``RomStorage``
    takes them, checked by its own rules; anything else is refused naming it."""
    from surrogate.rom.storage import RomStorage

    options = {k: v for k, v in (options or {}).items() if v is not None}
    unknown = sorted(set(options) - set(STORAGE_SETTINGS))
    if unknown:
        raise ValidationError("storage_options", f"only {', '.join(STORAGE_SETTINGS)}",
                              f"got {', '.join(unknown)}")
    storage = RomStorage(surface="rule", **options)  # no surface DEM: the checks only
    return {key: getattr(storage, key) for key in options}


def train(directory, out=None, n_mass_modes: int | None = None,
          n_velocity_modes: int | None = None, ridge: float | None = None,
          progress=None, target: str = "velocity",
          flux_floor: float | None = None, fill_law: str | None = None,
          rest_fraction: float | None = None, registration: str | None = None,
          validation=None, storage_options: dict | None = None,
          rom_seeds: int = VALIDATION_ROM_SEEDS,
          dispersivity: float | None = None,
          hanging_limit: float = HANGING_LIMIT, select_by: str = "mean",
          workers: int = 1) -> RomModel:
    """Fit a ``RomModel`` on ``directory``'s training samples (optionally save it).

    ``target`` (default "velocity"): the field the regression fits (``RomModel``);
    with "flux" the ``flux_floor`` left ``None`` is chosen among ``FLUX_FLOORS``
    with the other options; ``fill_law`` (default None; "dem" with "flux" only):
    ``RomModel``'s fitted fill, fitted in each fold of the selection too.
    ``rest_fraction`` (default None: fitted, ``surrogate.rom.rest.fit_samples``,
    its Youden table in the model's ``validation["rest"]``; 0: off): the resting
    bulk's share the model file keeps. ``registration`` (default None; "height"):
    ``RomModel``'s registered fit, its density the design's settled density
    (``surrogate.rom.packing.settled_density``), the candidates
    ``REGISTERED_CANDIDATES``. ``storage_options`` (default none;
    ``STORAGE_SETTINGS``): the ``RomStorage`` options the model is chosen under
    and keeps as its ``storage_settings``. ``dispersivity`` [m] (default None:
    the DEM's measured dispersivity less what the ROM's own scheme shows,
    ``rom_numerical_dispersivity``; 0: no random walk): the bulk's random walk.

    Options left ``None`` are chosen among ``MODEL_CANDIDATES`` by the
    smallest leave-one-run-out velocity error (recorded in the model's
    ``validation``), so the held-out scenario plays no part in the choice.
    With ``validation`` (the data folder of an exported held-out design, such
    as ``paper_validation``, or a list of them; velocity fits only) they are
    chosen by the smallest tracking error on its scenes instead
    (``surrogate.rom.validation``, ROM seeds 0 .. ``rom_seeds`` - 1, default
    ``VALIDATION_ROM_SEEDS``), each candidate fitted on the whole design and
    completed as the model is shipped, among the candidates whose bulk hangs over
    emptied cells by at most ``hanging_limit`` [-] at every scene's end (default
    ``surrogate.rom.hanging.HANGING_LIMIT``; should none, among all, and the
    record says so: ``hanging_limit_met``); ``select_by`` (``SELECT_BY``, default
    "mean") says what is minimised there; ``workers`` (default 1) validation scenes
    are scored at once, in processes of this machine, to the same scores.
    The training range of the mass distribution's residual is the larger of
    the training states' own and ``leave_one_run_out_residual`` (both in
    ``validation``).
    """
    from surrogate.rom.container import Container
    from surrogate.rom.validation import folders, tracking_scores

    storage_options = check_storage_options(storage_options)
    batch.code_version()  # the version trained with, read before the minutes of training
    if rest_fraction is not None:
        rest_fraction = float(check_finite_range("rest_fraction", rest_fraction, 0.0, 1.0))
    if dispersivity is not None:
        dispersivity = float(check_finite_range("dispersivity", dispersivity, 0.0, unit="m"))
    meta = doe.read_meta(directory)
    samples = doe.load_samples(directory)
    grid = Grid.from_dict(meta["grid"])
    container = Container.from_dict(meta["container"])
    if rest_fraction is not None:
        rest.check_share(rest_fraction, container)
    flux = target == "flux"
    if validation is not None:
        from surrogate.rom import heldout_layout

        if flux:
            raise ValidationError("validation", "a velocity fit (target 'velocity')",
                                  f"got target {target!r}")
        validation = folders(validation)
        for folder in validation:
            if not heldout_layout.is_heldout_data(folder):
                raise ValidationError("validation", "the data folder of an exported held-out "
                                      "design (`minetwin rom design --design paper_validation "
                                      "--export`)", f"{folder} is not one")
        rom_seeds = check_rom_seeds(rom_seeds)
        hanging_limit = float(check_finite_range("hanging_limit", hanging_limit, 0.0, 1.0))
        if select_by not in SELECT_BY:
            raise ValidationError("select_by", f"one of {', '.join(SELECT_BY)}",
                                  f"got {select_by!r}")
    # RomModel checks the registration's value when the first candidate is fitted
    registered = (registration, None if registration is None
                  else settled_density(directory)["density"])
    candidates = [c for c in (MODEL_CANDIDATES if registration is None
                              else REGISTERED_CANDIDATES)
                  if (n_mass_modes is None or c[0] == n_mass_modes)
                  and (n_velocity_modes is None or c[1] == n_velocity_modes)
                  and (ridge is None or c[2] == ridge)]
    if not candidates:
        candidates = [(n_mass_modes or 4, n_velocity_modes or n_mass_modes or 4,
                       1.0 if ridge is None else ridge)]
    floors = (FLUX_FLOORS if flux_floor is None else (flux_floor,)) if flux else (None,)
    everything = np.ones(samples["run"].size, dtype=bool)
    validation_record, model = {}, None
    if validation is not None and len(candidates) > 1:
        bases = fitted_bases(grid, samples, everything, registered)
        fitted, residuals = {}, {}
        for number, candidate in enumerate(candidates, start=1):
            _say(progress, f"candidate {number} of {len(candidates)}: modes "
                           f"{candidate[0]}/{candidate[1]}, ridge {candidate[2]:g}")
            fitted[candidate] = _completed(
                _fit(grid, container, samples, everything, *candidate, bases=bases,
                     registration=registered),
                directory, samples, meta.get("dem_config"), {}, rest_fraction,
                storage_options, residuals=residuals, walk=dispersivity)
        scores = tracking_scores(fitted, validation, rom_seeds, progress, workers=workers)
        resting = [key for key, entry in scores.items()
                   if entry["hanging_mass_share"] <= hanging_limit]
        criterion = "tracking_error" if select_by == "mean" else "floor_excess"
        best = min(resting or scores, key=lambda key: scores[key][criterion])
        model = fitted[best]
        names = [Path(folder).name for folder in validation]

        def by_candidate(score):
            return {_candidate_name(key): entry[score] for key, entry in scores.items()}

        validation_record = {
            "selected_by": "tracking on validation scenes",
            "validation_data": names[0] if len(names) == 1 else names, "rom_seeds": rom_seeds,
            "storage_settings": storage_options,
            "validation_tracking_error": scores[best]["tracking_error"],
            "validation_scenes": scores[best]["scenes"],
            "select_by": select_by,
            "validation_floor_excess": scores[best]["floor_excess"],
            "validation_scene_floors": scores[best]["scene_floors"],
            "candidates": by_candidate("tracking_error"),
            "candidates_floor_excess": by_candidate("floor_excess"),
            "hanging_limit": hanging_limit, "hanging_limit_met": bool(resting),
            "candidates_hanging_mass_share": by_candidate("hanging_mass_share")}
        if not resting:
            _say(progress, f"model selection: every candidate leaves more than {hanging_limit:g} "
                           "of its bulk hanging over emptied cells; chosen by tracking alone")
        _say(progress, f"model selection: modes {best[0]}/{best[1]}, ridge {best[2]:g}, "
                       f"tracking error {scores[best]['tracking_error']:.3f} on the "
                       f"validation scenes (at most {scores[best]['floor_excess']:.3f} over "
                       f"a scene's DEM floor), {len(resting)} of {len(scores)} candidates "
                       f"resting")
    elif len(candidates) * len(floors) > 1 and np.unique(samples["run"]).size > 1:
        scores = leave_one_run_out_errors(grid, samples, candidates, target, container,
                                          floors if flux else None, fill_law, registered)
        best = min(scores, key=scores.get)
        validation_record = {"leave_one_run_out_velocity_rel_error": scores[best],
                             "candidates": {_candidate_name(key): e
                                            for key, e in scores.items()}}
        _say(progress, f"model selection: modes {best[0]}/{best[1]}, ridge {best[2]:g}, "
                       + (f"flux floor {best[3]:g}, " if flux else "")
                       + f"leave-one-run-out velocity error {scores[best]:.3f}")
    else:
        best = (*candidates[0], floors[0]) if flux else candidates[0]
    if model is None:
        model = _completed(_fit(grid, container, samples, everything, *best[:3], target=target,
                                flux_floor=best[3] if flux else FLUX_FLOOR, fill_law=fill_law,
                                registration=registered),
                           directory, samples, meta.get("dem_config"), validation_record,
                           rest_fraction, storage_options, progress, walk=dispersivity)
    else:
        model.validation = {**validation_record, **model.validation}
    if out is not None:
        options = {"mass_modes": n_mass_modes, "velocity_modes": n_velocity_modes,
                   "ridge": ridge}
        if flux:  # a velocity fit's provenance stays as it was
            options.update(target=target, flux_floor=flux_floor)
        if fill_law is not None:
            options.update(fill_law=fill_law)
        if rest_fraction is not None:
            options.update(rest_fraction=rest_fraction)
        if dispersivity is not None:
            options.update(dispersivity=dispersivity)
        if registration is not None:
            options.update(registration=registration)
        if validation is not None:
            given = [str(folder) for folder in validation]
            options.update(validation=given[0] if len(given) == 1 else given,
                           rom_seeds=rom_seeds)
            if hanging_limit != HANGING_LIMIT:
                options.update(hanging_limit=hanging_limit)
            if select_by != "mean":
                options.update(select_by=select_by)
        options.update(storage_options)
        model.provenance = training_provenance(directory, out, options)
        model.save(out)
    return model


# ------------------------------------------------------------ evaluation
def run_storage(name: str, heldout: Path, model: RomModel | None = None, seed: int = 0,
                options: dict | None = None, on_step=None,
                build=None) -> tuple[dict, float, object]:
    """Drive storage model ``name`` through the held-out scenario.

    Returns ``(outflow, wall_s, storage)``; the wall time covers the storage
    model's calls only (receive, step), not the bookkeeping of this harness.
    ``on_step(k, time, storage)`` is called after every control step.
    ``build(rng=..., **options)`` makes the storage model instead of
    ``make_storage(name, ...)`` (a variant of the model ``name`` names).
    """
    from surrogate.dem import Dem

    initial = Dem.load_checkpoint(heldout / "initial.npz").snapshot()
    emissions = dict(np.load(heldout / "emissions.npz"))
    store = ParticleStore(capacity=4096)
    store.add_attribute("tracking_id", np.uint64, 0)
    t0 = float(initial["time"])
    order = np.argsort(initial["entry_time"], kind="stable")
    ids = store.add(mass=initial["mass"][order], f=initial["f"][order],
                    grade=initial["grade"][order], hardness=initial["hardness"][order],
                    owner=OWNER, time=t0, ids=initial["id"][order],
                    tracking_id=initial["tracking_id"][order])
    options = dict(options or {})
    if name == "rom":
        options.setdefault("model", model)
    build = build or partial(make_storage, name)
    storage = build(rng=np.random.default_rng(seed), **options)
    storage.bind(store, OWNER)
    if name == "rom":
        storage.place(ids, np.asarray(initial["position"])[order])
    else:
        storage.receive(ids, t0)
    steps = int(round(float(emissions["duration"]) / doe.CONTROL_STEP))
    rate = float(emissions["discharge_rate"])
    outflow = {k: [] for k in OUTFLOW_KEYS}
    wall = 0.0
    for k, rows in enumerate(_emission_batches(emissions, t0, steps)):
        t = t0 + k * doe.CONTROL_STEP
        new = store.add(mass=emissions["mass"][rows], f=doe.FEED_F,
                        grade=emissions["grade"][rows], hardness=emissions["hardness"][rows],
                        owner=OWNER, time=t, ids=emissions["id"][rows],
                        tracking_id=emissions["tracking_id"][rows])
        tic = time.perf_counter()
        storage.receive(new, t)
        leaving = storage.step(t, doe.CONTROL_STEP, rate)
        wall += time.perf_counter() - tic
        slots = store.slots(leaving)
        outflow["time"].append(np.full(leaving.size, t + doe.CONTROL_STEP))
        outflow["tracking_id"].append(store.attribute("tracking_id")[slots].copy())
        outflow["mass"].append(store.mass[slots].copy())
        outflow["grade"].append(store.grade[slots].copy())
        outflow["hardness"].append(store.hardness[slots].copy())
        store.remove_slots(slots)
        if on_step is not None:
            on_step(k, t + doe.CONTROL_STEP, storage)
    return {k: np.concatenate(v) for k, v in outflow.items()}, wall, storage


def score(outflow: dict, reference: dict, t0: float, t1: float, window: float = metrics.WINDOW_S) -> dict:
    """Tracking error and outflow grade/hardness errors against ``reference`` in
    ``window`` [s] windows."""
    return {"tracking_error": metrics.tracking_error(outflow, reference, t0, t1, window),
            "grade_error": metrics.outflow_signal_error(outflow, reference, "grade", t0, t1,
                                                        window),
            "hardness_error": metrics.outflow_signal_error(outflow, reference, "hardness",
                                                           t0, t1, window)}


FEED_HORIZON = 30.0
"""Horizon [s] of the feed prediction (paper: the funnel zone, next 30 s)."""


def _feed_forecaster(forecasts: list, dem: dict):
    """An ``on_step`` hook: every FEED_HORIZON seconds, the model's predicted
    feed grade and hardness for the next FEED_HORIZON seconds."""
    every = int(round(FEED_HORIZON / doe.CONTROL_STEP))
    rate = float(dem["discharge_rate"])

    def hook(k, t, storage):
        if (k + 1) % every:
            return
        ids, share = storage.predict(FEED_HORIZON, rate)
        if share.sum() <= 0:
            return
        slots = storage.particles.slots(ids)
        w = share / share.sum()
        forecasts.append((t, float(w @ storage.particles.grade[slots]),
                          float(w @ storage.particles.hardness[slots])))
    return hook


def _forecast_error(forecasts: list, reference: dict) -> dict:
    """Mean absolute error of predicted feed grade/hardness against the DEM's
    actual outflow over the same FEED_HORIZON seconds."""
    errors = {"grade": [], "hardness": []}
    time = reference["time"]
    for t, grade, hardness in forecasts:
        window = (time > t) & (time <= t + FEED_HORIZON)
        mass = reference["mass"][window]
        if mass.sum() <= 0:
            continue
        errors["grade"].append(abs(grade - mass @ reference["grade"][window] / mass.sum()))
        errors["hardness"].append(abs(hardness - mass @ reference["hardness"][window]
                                      / mass.sum()))
    return {k: float(np.mean(v)) if v else float("nan") for k, v in errors.items()}


def heldout_scenarios(directory) -> list[dict]:
    """The held-out scenarios of a data directory (``doe.json``; older
    directories hold the single ``heldout`` scenario)."""
    meta = doe.read_meta(directory)
    return meta["heldout_scenarios"] if "heldout_scenarios" in meta else [meta["heldout"]]


def evaluate_scenario(model: RomModel, heldout: Path, progress=None, rom_options=None,
                      rom_seeds: int = 1) -> dict:
    """Score FIFO, mixing and the ROM against every DEM replica in ``heldout``.

    ``tracking_error``, ``grade_error`` and ``hardness_error`` are the means over the
    replicas, ``tracking_error_spread`` the mean, min, max, standard deviation and
    count of the tracking error; the noise floor is the same error between every pair
    of replicas. The feed prediction and the velocity field are scored against the
    reference ``dem``. ``hanging_mass_share`` is the share of the bulk hanging over
    emptied cells at the scene's end (``surrogate.rom.hanging``), the ROM's mean over
    its seeds and the DEM's over the replicas' last mass fields.

    The ROM runs once per seed 0 .. ``rom_seeds`` - 1 (its surface layer and
    feeder draw random numbers): its errors are the means over seeds and
    replicas, its ``tracking_error_spread`` over every (seed, replica) pair, and
    ``rom_tracking_error_by_seed`` the per-seed means over the replicas. Its wall
    time, feed prediction, training-range check and field are seed 0's."""
    replicas = stable_replicas(heldout)
    if len(replicas) < 2:
        raise ValidationError("heldout", f"at least 2 stable DEM replicas in {heldout}",
                              f"found {len(replicas)}; rerun `minetwin rom evaluate` to make "
                              "them")
    dem, perturbed = replicas[0], replicas[1]
    t0 = float(dem["t0"])
    t1 = t0 + scenario_duration(heldout)
    references = [outflow_of(run) for run in replicas]
    reference = references[0]
    summary = {"tracking_error": {}, "grade_error": {}, "hardness_error": {},
               "tracking_error_spread": {}, "wall_s_per_simulated_s": {},
               "feed_prediction_error": {}, "dem_replicas": len(replicas)}
    for name in ("fifo", "mixing", "rom"):
        _say(progress, f"held-out run {heldout.name}: {name}")
        if name == "rom":  # steady-state timing: load the compiled kernels first
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                run_storage(name, heldout, model, options=rom_options)
        forecasts = []
        outflow, wall, storage = run_storage(name, heldout, model,
                                             options=rom_options if name == "rom" else None,
                                             on_step=_feed_forecaster(forecasts, dem))
        scores = [ensemble_score(outflow, references, t0, t1)]
        if name == "rom":
            summary["rom_out_of_training_range"] = sorted(storage.out_of_range.values())
            rom_storage = storage
            hanging = [hanging_at_end(storage, model, t1)]
            for seed in range(1, rom_seeds):
                _say(progress, f"held-out run {heldout.name}: rom, seed {seed}")
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # seed 0's run has warned
                    other, _, other_storage = run_storage(name, heldout, model, seed=seed,
                                                          options=rom_options)
                scores.append(ensemble_score(other, references, t0, t1))
                hanging.append(hanging_at_end(other_storage, model, t1))
            summary["hanging_mass_share"] = {
                "rom": float(np.mean(hanging)),
                "dem": float(np.mean([hanging_share(run["field_mass"][-1], model.grid,
                                                    model.container) for run in replicas]))}
            summary["rom_seeds"] = rom_seeds
            summary["rom_tracking_error_by_seed"] = [s["tracking_error"] for s in scores]
        for key in ("tracking_error", "grade_error", "hardness_error"):
            summary[key][name] = float(np.mean([s[key] for s in scores]))
        summary["tracking_error_spread"][name] = spread(
            [e for s in scores for e in s["tracking_errors"]])
        summary["wall_s_per_simulated_s"][name] = wall / (t1 - t0)
        summary["feed_prediction_error"][name] = _forecast_error(forecasts, reference)
    floor = noise_floor(references, t0, t1)
    summary["tracking_error_dem_noise_floor"] = floor["tracking_error"]
    summary["tracking_error_spread"]["dem_noise_floor"] = floor["tracking_error_spread"]
    summary["grade_error"]["dem_noise_floor"] = floor["grade_error"]
    summary["hardness_error"]["dem_noise_floor"] = floor["hardness_error"]
    summary["wall_s_per_simulated_s"]["dem"] = float(dem["wall_s"]) / (t1 - t0)
    summary["speedup_vs_dem"] = (summary["wall_s_per_simulated_s"]["dem"]
                                 / summary["wall_s_per_simulated_s"]["rom"])
    rate = float(dem["discharge_rate"])
    inflow = float(np.load(heldout / "emissions.npz")["mass"].sum()) / (t1 - t0)
    # the field the ROM moves its bulk by (its velocity model), at the DEM's states
    predicted = np.array([rom_storage.predicted_field(m, rate, inflow)
                          for m in dem["field_mass"]])
    summary["velocity_field_rel_error"] = metrics.velocity_field_rel_error(
        predicted, dem["field_velocity"], dem["field_mass"])
    # the same error between two DEM runs 1e-6 m apart: the part of the
    # velocity field no deterministic model can predict
    summary["velocity_field_rel_error_dem_noise_floor"] = metrics.velocity_field_rel_error(
        perturbed["field_velocity"], dem["field_velocity"], dem["field_mass"])
    summary["simulated_s"] = t1 - t0
    # the mass the DEM piles held over the scene: where the scores were measured
    held = np.concatenate([np.asarray(run["field_mass"]).reshape(len(run["field_mass"]), -1)
                           .sum(axis=1) for run in replicas])
    summary["held_mass_range_kg"] = [float(held.min()), float(held.max())]
    summary["dem_particles"] = int(dem["particles"])
    summary["dem_dt_s"] = float(dem["dt"])
    return summary


def hanging_at_end(storage, model: RomModel, t: float) -> float:
    """Share of the ROM's bulk hanging over emptied cells at time ``t`` [s]
    (``surrogate.rom.hanging``), on the model's grid and container."""
    bulk = storage.bulk_snapshot(t)
    return hanging_share_of(bulk["position"], bulk["mass"], model.grid, model.container)


def _targets(scenario: dict) -> dict:
    """The ROM's pass conditions on one held-out scenario: tracking error at most
    0.10 and within 0.02 of the DEM replicas' noise floor, below FIFO and mixing,
    at least 100x faster than the DEM and at least 20x real time (wall clock,
    surface layer included)."""
    tracking = scenario["tracking_error"]
    floor = scenario["tracking_error_dem_noise_floor"]
    return {"tracking_error_at_most_0.10": bool(tracking["rom"] <= 0.10),
            "tracking_error_within_0.02_of_dem_noise_floor": bool(
                tracking["rom"] - floor <= 0.02),
            "tracking_error_below_fifo_and_mixing": bool(
                tracking["rom"] < min(tracking["fifo"], tracking["mixing"])),
            "speedup_at_least_100": bool(scenario["speedup_vs_dem"] >= 100.0),
            "realtime_factor_at_least_20": bool(
                1.0 / scenario["wall_s_per_simulated_s"]["rom"] >= 20.0)}


AGGREGATE_NOTE = ("top-level tracking_error, tracking_error_dem_noise_floor, grade_error, "
                  "hardness_error, feed_prediction_error, velocity_field_rel_error and "
                  "velocity_field_rel_error_dem_noise_floor are means over the held-out scenarios (per scenario: 'scenarios'); "
                  "wall_s_per_simulated_s is total wall time over total simulated time of "
                  "all of them, speedup_vs_dem the DEM's over the ROM's; a target is met "
                  "only if it is met on every scenario; the ROM's errors are means over "
                  "its seeds 0 .. rom_seeds - 1 as well (per scenario and seed: "
                  "'rom_tracking_error_by_seed'), its wall time seed 0's")


def _mean(values: list):
    """Mean of numbers, or key by key of (nested) dicts of numbers."""
    if isinstance(values[0], dict):
        return {k: _mean([v[k] for v in values]) for k in values[0]}
    return float(np.mean(values))


def check_rom_seeds(rom_seeds) -> int:
    """The number of ROM seeds ``evaluate`` scores, refused outside 1-100."""
    whole = (isinstance(rom_seeds, (int, np.integer)) and not isinstance(rom_seeds, bool))
    if not whole or not 1 <= rom_seeds <= 100:
        raise ValidationError("rom_seeds", "a whole number of seeds, 1-100", f"got {rom_seeds!r}")
    return int(rom_seeds)


def evaluate(model: RomModel, directory, progress=None, rom_options=None,
             executor=None, rom_seeds: int = 1) -> dict:
    """Score FIFO, mixing and the ROM on every held-out scenario; the summary dict
    (aggregation: ``AGGREGATE_NOTE``). With ``executor`` (``cosim.batch``) the
    scenarios are scored as parallel tasks; the scores are the same, only the
    wall times differ (each is measured in its own worker)."""
    rom_seeds = check_rom_seeds(rom_seeds)
    metas = heldout_scenarios(directory)
    calls = [(evaluate_scenario, {"model": model, "heldout": Path(directory) / meta["name"],
                                  "progress": progress, "rom_options": rom_options,
                                  "rom_seeds": rom_seeds})
             for meta in metas]
    results = (batch.run_calls(calls, executor) if executor is not None
               else [function(**kwargs) for function, kwargs in calls])
    scenarios = {}
    for meta, result in zip(metas, results):
        result["scenario"] = meta
        result["targets"] = _targets(result)
        scenarios[meta["name"]] = result
    runs = list(scenarios.values())
    summary = {"aggregate": AGGREGATE_NOTE, "window_s": metrics.WINDOW_S,
               "rom_seeds": rom_seeds, "heldout": [s["scenario"] for s in runs]}
    for key in ("tracking_error", "tracking_error_dem_noise_floor", "grade_error",
                "hardness_error", "feed_prediction_error", "velocity_field_rel_error",
                "velocity_field_rel_error_dem_noise_floor"):
        summary[key] = _mean([s[key] for s in runs])
    simulated = sum(s["simulated_s"] for s in runs)
    summary["wall_s_per_simulated_s"] = {
        name: sum(s["wall_s_per_simulated_s"][name] * s["simulated_s"] for s in runs) / simulated
        for name in runs[0]["wall_s_per_simulated_s"]}
    wall = summary["wall_s_per_simulated_s"]
    summary["speedup_vs_dem"] = wall["dem"] / wall["rom"]
    summary["targets"] = {key: all(s["targets"][key] for s in runs) for key in runs[0]["targets"]}
    summary["scenarios"] = scenarios
    summary["model"] = model.header()
    summary["rom_options"] = {k: v for k, v in (rom_options or {}).items()
                              if isinstance(v, (str, int, float, bool))}
    return summary


def write_summary(summary: dict, out_dir) -> Path:
    """``out_dir/summary.json``, strict JSON (a NaN is refused, not written)."""
    from cosim import jsonio

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return jsonio.write(out_dir / "summary.json", summary, indent=1)
