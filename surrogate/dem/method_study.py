"""The error of each DEM method as a function of its cost, and where each fails (issue 22).

Three small scenes, each run from one saved start state by every method
setting, at two contact stiffnesses:

* ``settled``: a packed pile (``packed_pile``) settled at rest; it should stay
  as it is. Observables: mean and largest penetration (overlap over the
  smaller diameter) at the end, angle of repose.
* ``funnel``: a bunker with a raised floor and an opening (the scene of
  ``examples/dem_orifice.py``: disks laid on a lattice flow out under
  gravity; a sink below takes them). Tracking ids are 1 m height bands, so
  the outflow's composition over time says what left in which order.
  Observables: discharge rate after ``skip`` against the reference and
  against the 2D Beverloo law (``DemConfig.orifice_capacity``, Beverloo,
  Leniger and van de Velde 1961, Chem. Eng. Sci. 15:260), and the tracking
  error of the outflow (``surrogate.rom.metrics.tracking_error``: mean
  total-variation distance of the per-window outflow compositions).
* ``inflow``: a settled small pile fed from the left inlet for
  ``inflow_s`` at ``inflow_rate``, then left for the rest of the scene.
  Observables: angle of repose (``surrogate.dem.analysis.angle_of_repose``
  of the disks slower than ``RESTING_SPEED``) and penetration at the end.

Stiffnesses: ``soft``, the DEM's default k_n = 4e7 N/m; ``rock``, a
realistic rock stiffness: granite, Young's modulus E = 50 GPa, Poisson's
ratio 0.25, E* = E / (2 (1 - nu^2)) = 26.7 GPa, and a per-contact stiffness
of the order of E* d with d = 0.376 m the mean diameter: k_n = 1e10 N/m
(250 x the soft one, contact time 16 x shorter). Each scene's start state
is built at its stiffness (the same layout and disks; a pile is settled by
the explicit DEM at its stable step for at most ``SETTLE_S``).

Methods, on each scene and stiffness (from the same start state):

* the reference: explicit at 0.25 stable steps (``stable_dt`` = t_c / 15), and
  a replica of it started from the state moved by 1e-6 m, whose distance to
  the reference is each observable's noise floor;
* explicit at 0.5, 1, 2, 4 and 8 stable steps (``EXPLICIT_FACTORS``);
* nonsmooth (``nonsmooth.py``) at 1, 2, 5, 11 and 20 ms with 10, 25, 50, 100
  and 200 projected Gauss-Seidel sweeps at most (``solver_tolerance``
  1e-6 m/s ends a solve earlier), each with the paper's plain sweeps
  (``solver_relaxation`` 1) and over-relaxed at ``OVER_RELAXATION`` (1.9;
  projected SOR of the normal impulses, Cryer 1971, ``DemConfig.solver_relaxation``).

Failures, by stated criteria (``FAILURE_CRITERIA``): an explicit run that
blows up is stopped by the DEM's guard (``DemBlowUp``: what, time and
cause are recorded); a nonsmooth run *compresses* when its mean
penetration at the end exceeds ``COMPRESSION_FACTOR`` (3) x the mean overlap
of the reference or of its replica, the larger, or its largest exceeds ``MAX_PENETRATION`` (10 %) of the
smaller diameter; it *leaks* when a disk's centre gets below the floor
(y < 0), or in the funnel below the raised floor more than one largest
diameter beside the opening, or the guard finds one outside the container;
it *jams* when the funnel's discharge rate is below ``JAM_FRACTION`` (0.5)
of the reference's. Each failure gets a picture of the pile at the failure
(``surrogate.dem.plots.pile_pictures``, coloured by speed).

Cost: wall seconds per simulated second of the run itself (start-up and
compilation excluded), on one core per run.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cosim import numerics
from surrogate.dem.analysis import angle_of_repose
from surrogate.dem.builders import config_for_particles, packed_pile, settle
from surrogate.dem.config import DemConfig
from surrogate.dem.simulation import Dem, DemBlowUp

SOFT_STIFFNESS = 4.0e7
"""Today's normal stiffness k_n [N/m]."""
ROCK_YOUNG_MODULUS = 50e9
"""Young's modulus of granite [Pa]."""
ROCK_POISSON = 0.25
"""Poisson's ratio of granite [-]."""
ROCK_STIFFNESS = 1.0e10
"""Per-contact stiffness of rock, ~ E* d (module docstring) [N/m]."""
STIFFNESSES = {"soft": SOFT_STIFFNESS, "rock": ROCK_STIFFNESS}
SETTLE_S = 4.0
"""Longest settling of a pile's start state [s]."""

REFERENCE_FACTOR = 0.25
EXPLICIT_FACTORS = (0.5, 1.0, 2.0, 4.0, 8.0)
NONSMOOTH_STEPS = (0.001, 0.002, 0.005, 0.011, 0.02)
NONSMOOTH_ITERATIONS = (10, 25, 50, 100, 200)
OVER_RELAXATION = 1.9
"""The over-relaxation [-] the study runs beside the plain sweeps: the value that
held the rock-stiffness paper-scale pile at rest at 100 sweeps
(``surrogate/dem/README.md``)."""
NONSMOOTH_RELAXATIONS = (1.0, OVER_RELAXATION)
PERTURBATION = 1e-6
"""Shift of the replica's start positions [m]."""

RESTING_SPEED = 1.0
"""The angle of repose is measured on the disks slower than this [m/s], so
that a disk still falling from the inlet is not taken for the crest."""
COMPRESSION_FACTOR = 3.0
MAX_PENETRATION = 0.1
JAM_FRACTION = 0.5
FAILURE_CRITERIA = {
    "blow-up": "the DEM's guard stopped the run (DemBlowUp: speed, container, energy or "
               "overlap)",
    "compressed": f"mean penetration at the end > {COMPRESSION_FACTOR:g} x the mean overlap of the "
                  "reference or of its replica (the larger), or the largest > "
                  f"{MAX_PENETRATION:g} of the smaller diameter",
    "leaked": "a disk centre below the floor (y < 0), in the funnel below the raised floor "
              "more than one largest diameter beside the opening, or outside the container",
    "jammed": f"funnel discharge rate < {JAM_FRACTION:g} x the reference's",
}


@dataclass(frozen=True)
class StudySize:
    """Sizes and durations of the scenes [disks, s, m, kg/s]."""

    settled_particles: int = 150
    settled_s: float = 1.5
    funnel_width: float = 7.0
    funnel_fill: float = 5.0
    funnel_opening: float = 3.0
    funnel_s: float = 2.0
    funnel_skip: float = 0.5
    inflow_particles: int = 100
    inflow_rate: float = 2000.0
    inflow_s: float = 0.8
    inflow_total_s: float = 1.8
    window: float = 0.25
    explicit_factors: tuple = EXPLICIT_FACTORS
    nonsmooth_steps: tuple = NONSMOOTH_STEPS
    nonsmooth_iterations: tuple = NONSMOOTH_ITERATIONS
    nonsmooth_relaxations: tuple = NONSMOOTH_RELAXATIONS


FULL = StudySize()
QUICK = StudySize(settled_particles=60, settled_s=0.5, funnel_width=5.0, funnel_fill=3.0,
                  funnel_opening=2.5, funnel_s=1.2, funnel_skip=0.5, inflow_particles=50,
                  inflow_s=0.3, inflow_total_s=1.1, window=0.2,
                  explicit_factors=(1.0, 8.0), nonsmooth_steps=(0.002, 0.02),
                  nonsmooth_iterations=(10, 100))

FUNNEL_FLOOR_Y = 1.0
"""Height of the funnel's raised floor [m]; the sink below takes disks whose
centre is under ``FUNNEL_SINK_Y``, so a disk through the opening is counted
about 0.3 s after it left (``funnel_skip`` leaves that start-up out)."""
FUNNEL_SINK_Y = 0.6


# ------------------------------------------------------------------ scenes
def _f16():
    f16 = np.zeros(16)
    f16[12] = 1.0
    return f16


def build_funnel(size: StudySize, stiffness: float, seed: int = 0) -> Dem:
    """The funnel scene at rest (module docstring) at ``stiffness`` [N/m];
    tracking id = 1 m band. Laid on a lattice without contacts: nothing to
    settle."""
    half, b = size.funnel_width / 2.0, size.funnel_opening
    cfg = DemConfig(normal_stiffness=stiffness, floor_width=size.funnel_width,
                    side_wall_height=FUNNEL_FLOOR_Y + size.funnel_fill + 1.0,
                    extra_walls=[[-half, FUNNEL_FLOOR_Y, -b / 2, FUNNEL_FLOOR_Y],
                                 [b / 2, FUNNEL_FLOOR_Y, half, FUNNEL_FLOOR_Y]],
                    inlets=[[0.0, FUNNEL_FLOOR_Y + size.funnel_fill + 0.5]], outlets=[0.0],
                    outlet_width=size.funnel_width - 1.0, feeder_zone_height=FUNNEL_SINK_Y,
                    max_discharge_rate=1e6)
    rng = np.random.default_rng(seed)
    pitch = cfg.diameter_max + 1e-3
    xs = np.arange(-half + pitch / 2, half - pitch / 2, pitch)
    ys = np.arange(FUNNEL_FLOOR_Y + pitch / 2, FUNNEL_FLOOR_Y + size.funnel_fill, pitch)
    grid = np.array([(x, y) for y in ys for x in xs])
    diameters = numerics.cbrt(rng.uniform(cfg.diameter_min ** 3, cfg.diameter_max ** 3,
                                          len(grid)))
    dem = Dem(cfg, seed=seed)
    band = np.floor(grid[:, 1] - FUNNEL_FLOOR_Y).astype(np.int64)
    dem.place(grid, cfg.sphere_mass(diameters), 0.5, 1.0, _f16(), band)
    return dem


def build_pile(n: int, stiffness: float, seed: int = 0) -> Dem:
    """A packed pile of ``n`` disks at ``stiffness`` [N/m] settled at rest
    (explicit DEM at its stable step; at most ``SETTLE_S``)."""
    base = DemConfig(normal_stiffness=stiffness)
    dem = packed_pile(config_for_particles(n, base), n, seed=seed)
    settle(dem, max_time=SETTLE_S, speed=0.02, chunk=0.25)
    return dem


def build_start_state(scene: str, stiffness: str, size: StudySize, folder: str,
                      seed: int = 0) -> str:
    """Write the start state of ``scene`` at ``stiffness`` ("soft" or "rock")
    to ``folder``; returns the checkpoint's path."""
    k_n = STIFFNESSES[stiffness]
    if scene == "funnel":
        dem = build_funnel(size, k_n, seed)
    elif scene == "settled":
        dem = build_pile(size.settled_particles, k_n, seed)
    else:
        dem = build_pile(size.inflow_particles, k_n, seed + 1)
    path = Path(folder) / f"start_{scene}_{stiffness}.npz"
    dem.save_checkpoint(path)
    return str(path)


def build_start_states(size: StudySize, folder: Path, executor, seed: int = 0) -> dict:
    """Checkpoint path per (scene, stiffness), built on ``executor``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    from cosim import batch

    keys = [(scene, stiffness) for scene in ("settled", "funnel", "inflow")
            for stiffness in STIFFNESSES]
    calls = [(build_start_state, {"scene": scene, "stiffness": stiffness, "size": size,
                                  "folder": str(folder), "seed": seed})
             for scene, stiffness in keys]
    return dict(zip(keys, batch.run_calls(calls, executor)))


# ------------------------------------------------------------------ runs
def _leaked(dem: Dem, scene: str, size: StudySize) -> str | None:
    if dem.n == 0:
        return None
    below = dem.pos[:, 1] < 0.0
    if below.any():
        k = int(np.argmax(below))
        return f"disk id {int(dem.id[k])} below the floor at y = {dem.pos[k, 1]:.3g} m"
    if scene == "funnel":
        beside = ((dem.pos[:, 1] < FUNNEL_FLOOR_Y - dem.radius)
                  & (np.abs(dem.pos[:, 0]) > size.funnel_opening / 2 + dem.cfg.diameter_max))
        if beside.any():
            k = int(np.argmax(beside))
            return (f"disk id {int(dem.id[k])} through the raised floor at x = "
                    f"{dem.pos[k, 0]:.3g} m, y = {dem.pos[k, 1]:.3g} m")
    return None


def _picture(snapshot: dict, folder: Path, name: str) -> str:
    """Pictures of the pile (``plots.pile_pictures``) in ``folder/name``; the
    path of the one coloured by speed."""
    from surrogate.dem import plots

    paths = plots.pile_pictures(snapshot, Path(folder) / name, run=name)
    return str(next(p for p in paths if p.name == "pile_speed.png"))


def run_method(start: str, scene: str, stiffness: str, method: str, size: StudySize,
               factor: float | None = None, dt: float | None = None,
               iterations: int | None = None, replica: int = 0,
               pictures: str | None = None, relaxation: float = 1.0) -> dict:
    """One run of ``scene`` from the checkpoint ``start``: the row of the table
    (observables, cost, failure if any; see the module docstring)."""
    changes = {"method": method}
    if iterations is not None:
        changes["solver_iterations"] = int(iterations)
    if relaxation != 1.0:
        changes["solver_relaxation"] = float(relaxation)
    dem = Dem.load_checkpoint(start, changes)
    if replica:
        rng = np.random.default_rng(1000 + replica)
        dem.pos += rng.uniform(-PERTURBATION, PERTURBATION, dem.pos.shape)
    step = factor * dem.stable_dt if method == "explicit" else dt
    dem.set_dt(step, force=method == "explicit" and factor > 1)
    warm = Dem.load_checkpoint(start, changes)  # compiles or loads the kernels untimed
    warm.set_dt(step, force=method == "explicit" and factor > 1)
    warm.step(1)
    if scene == "funnel":
        # a sink: the most the feeder's own zone passes, far above the opening's flow
        dem.set_discharge_rate(min(dem.cfg.max_discharge_rate, dem.cfg.orifice_capacity()))
    duration = {"settled": size.settled_s, "funnel": size.funnel_s,
                "inflow": size.inflow_total_s}[scene]
    t0 = dem.time
    chunk = 0.05
    failure, skipped_mass, lot = None, 0.0, 0
    outflow = {k: [] for k in ("time", "tracking_id", "mass")}
    wall = 0.0
    while dem.time - t0 < duration - 1e-9 and failure is None:
        if scene == "inflow" and dem.time - t0 < size.inflow_s - 1e-9:
            dem.emit(size.inflow_rate * chunk, 0.5, 1.0, _f16(), 1_000 + lot, inlet=0)
            lot += 1
        tic = time.perf_counter()
        try:
            dem.advance(min(chunk, duration - (dem.time - t0)))
        except DemBlowUp as exc:
            failure = {"kind": "blow-up", "what": exc.kind, "time_s": exc.time - t0,
                       "reason": f"{exc.seen}; {exc.cause}"}
            if method == "nonsmooth" and exc.kind in ("outside", "overlap"):
                failure["kind"] = "leaked" if exc.kind == "outside" else "compressed"
        wall += time.perf_counter() - tic
        out = dem.discharged()
        if dem.time - t0 <= size.funnel_skip + 1e-9 and scene == "funnel":
            skipped_mass += float(out["mass"].sum())
        for k in outflow:
            outflow[k].append(out[k])
        if failure is None and method == "nonsmooth":
            leak = _leaked(dem, scene, size)
            if leak:
                failure = {"kind": "leaked", "what": "leak", "time_s": dem.time - t0,
                           "reason": leak}
    simulated = dem.time - t0
    mean_ov, max_ov = dem.overlap_stats()
    row = {"scene": scene, "stiffness": stiffness, "normal_stiffness_N_m": dem.cfg.normal_stiffness,
           "method": method, "dt_s": dem.dt, "stable_dt_s": dem.stable_dt,
           "dt_over_stable": dem.dt / dem.stable_dt if method == "explicit" else None,
           "iterations": iterations,
           "relaxation": relaxation if method == "nonsmooth" else None, "replica": replica,
           "simulated_s": simulated, "wall_s": wall,
           "wall_s_per_simulated_s": wall / simulated if simulated > 0 else None,
           "mean_sweeps_per_step": (float(dem.solver_stats[1] / dem.solver_stats[0])
                                    if method == "nonsmooth" and dem.solver_stats[0] else None),
           "particles": dem.n, "mean_penetration": mean_ov, "max_penetration": max_ov,
           "angle_of_repose_deg": None, "discharge_rate_kg_s": None, "beverloo_kg_s": None,
           "failure": failure}
    outflow = {k: np.concatenate(v) if v else np.empty(0) for k, v in outflow.items()}
    if failure is None:
        if scene in ("settled", "inflow"):
            resting = np.hypot(dem.vel[:, 0], dem.vel[:, 1]) < RESTING_SPEED
            angle = angle_of_repose(dem.pos[resting], dem.radius[resting])
            row["angle_of_repose_deg"] = None if math.isnan(angle) else angle
        if scene == "funnel":
            out_mass = float(outflow["mass"].sum()) - skipped_mass
            row["discharge_rate_kg_s"] = out_mass / max(duration - size.funnel_skip, 1e-9)
            row["beverloo_kg_s"] = dem.cfg.orifice_capacity(size.funnel_opening)
    row["outflow"] = {"time": (outflow["time"] - t0).tolist(),
                      "tracking_id": outflow["tracking_id"].astype(np.int64).tolist(),
                      "mass": outflow["mass"].tolist()}
    if pictures:
        if failure is not None:
            failure["picture"] = _picture(dem.snapshot(), Path(pictures), run_label(row))
        elif method == "nonsmooth":  # kept for a picture if evaluate finds a failure
            path = Path(pictures) / f"{run_label(row)}_end.npz"
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(path, **dem.snapshot())
            row["end_state"] = str(path)
    return row


def run_label(row: dict) -> str:
    """A file-safe name of a run."""
    if row["method"] == "explicit":
        how = f"explicit_{row['dt_over_stable']:.3g}x"
    else:
        how = f"nonsmooth_{row['dt_s'] * 1e3:.3g}ms_{row['iterations']}it"
        if row.get("relaxation", 1.0) != 1.0:
            how += f"_sor{row['relaxation']:g}"
    return f"{row['scene']}_{row['stiffness']}_{how}_r{row['replica']}"


def plan(paths: dict, size: StudySize, pictures: str) -> list[tuple]:
    """The runs, as ``(function, kwargs)`` calls for ``cosim.batch.run_calls``,
    costliest first (the rock references) so the pool ends together."""
    calls = []
    for (scene, stiffness), start in paths.items():
        common = {"start": str(start), "scene": scene, "stiffness": stiffness,
                  "size": size, "pictures": pictures}
        for replica in (0, 1):
            calls.append((run_method, {**common, "method": "explicit",
                                       "factor": REFERENCE_FACTOR, "replica": replica}))
        for factor in size.explicit_factors:
            calls.append((run_method, {**common, "method": "explicit", "factor": factor}))
        for dt in size.nonsmooth_steps:
            for iterations in size.nonsmooth_iterations:
                for relaxation in size.nonsmooth_relaxations:
                    calls.append((run_method, {**common, "method": "nonsmooth", "dt": dt,
                                               "iterations": iterations,
                                               "relaxation": relaxation}))

    def cost(call):
        kw = call[1]
        scale = ROCK_STIFFNESS / SOFT_STIFFNESS if kw["stiffness"] == "rock" else 1.0
        if kw["method"] == "explicit":
            return math.sqrt(scale) / kw["factor"]
        return kw["iterations"] / (kw["dt"] * 1e3) / 20.0

    return sorted(calls, key=cost, reverse=True)


# ------------------------------------------------------------------ analysis
def evaluate(rows: list[dict], size: StudySize) -> list[dict]:
    """Errors against the reference, noise floors and the nonsmooth failure
    criteria; returns the table rows (outflows dropped)."""
    from surrogate.rom.metrics import tracking_error

    groups: dict = {}
    for row in rows:
        groups.setdefault((row["scene"], row["stiffness"]), []).append(row)
    table = []
    for (scene, stiffness), group in sorted(groups.items()):
        refs = [r for r in group if r["method"] == "explicit"
                and abs(r["dt_over_stable"] - REFERENCE_FACTOR) < 1e-9]
        ref = next(r for r in refs if r["replica"] == 0)
        replica = next((r for r in refs if r["replica"] == 1), None)
        end = {"funnel": size.funnel_s, "settled": size.settled_s,
               "inflow": size.inflow_total_s}[scene]

        def errors(row):
            out = {"angle_error_deg": None, "discharge_rate_error": None,
                   "penetration_ratio_to_reference": None, "tracking_error": None}
            if row["failure"] is not None:  # stopped during the run: no observables
                return out
            if row["angle_of_repose_deg"] is not None and ref["angle_of_repose_deg"] is not None:
                out["angle_error_deg"] = abs(row["angle_of_repose_deg"]
                                             - ref["angle_of_repose_deg"])
            if scene == "funnel" and ref["discharge_rate_kg_s"]:
                out["discharge_rate_error"] = abs(row["discharge_rate_kg_s"]
                                                  - ref["discharge_rate_kg_s"]) \
                    / ref["discharge_rate_kg_s"]
                err = tracking_error(row["outflow"], ref["outflow"], 0.0, end, size.window)
                out["tracking_error"] = None if math.isnan(err) else err
            if ref["mean_penetration"] > 0:
                out["penetration_ratio_to_reference"] = (row["mean_penetration"]
                                                         / ref["mean_penetration"])
            return out

        floor = errors(replica) if replica is not None else {}
        # the compression limit scales the larger mean overlap of the reference
        # and its replica: in a scene with impacts under way it varies by run
        overlap = max(ref["mean_penetration"],
                      replica["mean_penetration"] if replica is not None else 0.0)
        for row in group:
            entry = {k: v for k, v in row.items() if k != "outflow"}
            entry.update(errors(row))
            entry["noise_floor"] = floor
            entry["reference"] = row is ref
            entry.pop("end_state", None)
            if row["method"] == "nonsmooth" and row["failure"] is None:
                entry["failure"] = _nonsmooth_failure(row, ref, overlap, scene)
                if entry["failure"] is not None and row.get("end_state"):
                    with np.load(row["end_state"]) as data:
                        snapshot = {k: data[k] for k in data.files}
                    folder = Path(row["end_state"]).parent
                    entry["failure"]["picture"] = _picture(snapshot, folder, run_label(row))
            if row.get("end_state"):
                Path(row["end_state"]).unlink(missing_ok=True)
            table.append(entry)
    return table


def _nonsmooth_failure(row: dict, ref: dict, overlap: float, scene: str) -> dict | None:
    mean_limit = COMPRESSION_FACTOR * overlap
    if row["mean_penetration"] > mean_limit or row["max_penetration"] > MAX_PENETRATION:
        return {"kind": "compressed", "what": "penetration", "time_s": row["simulated_s"],
                "reason": (f"mean penetration {row['mean_penetration']:.3g} (limit "
                           f"{mean_limit:.3g}: {COMPRESSION_FACTOR:g} x the reference's or "
                           "its replica's, the larger), "
                           f"largest {row['max_penetration']:.3g} (limit {MAX_PENETRATION:g}) "
                           "of the smaller diameter")}
    if (scene == "funnel" and ref["discharge_rate_kg_s"]
            and row["discharge_rate_kg_s"] < JAM_FRACTION * ref["discharge_rate_kg_s"]):
        return {"kind": "jammed", "what": "discharge", "time_s": row["simulated_s"],
                "reason": (f"discharge rate {row['discharge_rate_kg_s']:.4g} kg/s, below "
                           f"{JAM_FRACTION:g} x the reference's "
                           f"{ref['discharge_rate_kg_s']:.4g} kg/s")}
    return None
