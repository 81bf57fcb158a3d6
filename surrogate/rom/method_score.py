"""Another DEM method's runs of the held-out scenes, scored against the explicit DEM's replicas.

Source: the method comparison asks for the stockpile tracking error of each DEM
method with the noise floor beside it, at the paper's scale (Servin, Wang,
Lacoursière and Bodin 2014 for the nonsmooth method; ``surrogate/dem/README.md``).
The metric is ``surrogate.rom.evaluate``'s: the tracking error of the outflow
composition in 30 s windows (``metrics.tracking_error``) against each explicit
replica of the scene, averaged, with its spread; the noise floor is the explicit
replicas' error among themselves (``evaluate.noise_floor``). The method's runs
come from a held-out design of that method (``paper_design.
paper_heldout_nonsmooth_design``: the same scenes, inflow, feed seeds and tracking
ids), exported with ``minetwin rom design --export``; a scene is scored when a
run of the method and at least 2 explicit replicas of it finished. The method is
chaotic too: each of its finished runs of a scene is one realisation (a design
with replicas of that method, start states 1e-6 m apart), scored against every
explicit replica (``realisations``); the scene's errors are the means over the
realisations, ``tracking_error_spread`` spans every realisation against every
replica, ``realisation_spread`` the realisations' own errors.

Cost is wall and CPU seconds per simulated second of each run's record (the
explicit DEM's: the mean over its replicas); the machines' load differed, so the
CPU figure is the comparable one.

A jam the blow-up guard cannot see: the feeder takes exactly its set rate while
material reaches it, so every explicit replica delivers the set mass; a method
whose pile does not refill the feeder zone delivers less. A scene is ``jammed``
when the method's feeder delivered less than ``JAM_DELIVERED_SHARE`` of the
explicit replicas' mean mass (the small-scene study's criterion, a funnel rate
under half the reference's, is for an orifice without a set rate), in any
realisation.

A creep the outflow cannot see either: a pile that should rest beside the funnel
keeps moving (an unconverged projected Gauss-Seidel leaves velocity in the
bulk), while the feeder still delivers its set rate. ``bulk_speed_m_s`` is the
mass-weighted mean speed of the ROM-grid cells whose centre lies more than
``BULK_DISTANCE`` from the feeder's centre, averaged over the run's samples (the compact
result's displacement velocity, ``surrogate.rom.grid``); a scene is ``creeping``
when the method's exceeds ``CREEP_FACTOR`` times every explicit replica's (the
small-scene study's compression criterion: 3 times the reference's) in any
realisation.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cosim.errors import ValidationError
from surrogate.rom import metrics
from surrogate.rom.evaluate import OUTFLOW_KEYS, ensemble_score, noise_floor, spread
from surrogate.rom.heldout_layout import finished_scenes, scene_of


JAM_DELIVERED_SHARE = 0.9
"""Share [-] of the explicit replicas' mean discharged mass under which a method's
run is ``jammed`` (module docstring)."""

BULK_DISTANCE = 12.0
"""Distance [m] from the feeder's centre beyond which the pile is the resting bulk:
the 8 m feeder's funnel of the explicit DEM moves it at 0.001-0.006 m/s there
(the rock scenes' replicas, 20 s)."""

CREEP_FACTOR = 3.0
"""Ratio [-] of a method's ``bulk_speed_m_s`` to every explicit replica's above which
its scene is ``creeping`` (module docstring)."""


def _done_runs(data: Path) -> dict:
    """Finished runs of an exported design by scene (the name without ``_r<k>``)."""
    manifest = data / "manifest.json"
    if not manifest.is_file():
        raise ValidationError("--data", "an exported design folder with manifest.json "
                              "(`minetwin rom design ... --export`)", f"{data} has none")
    records = json.loads(manifest.read_text())
    unstable = {scene_of(record): record for record in records.get("runs_unstable", [])}
    return {"design": records.get("design"), "dem_config": records.get("dem_config", {}),
            "scenes": finished_scenes(records["runs"]), "unstable": unstable}


def _outflow(data: Path, record: dict) -> dict:
    with np.load(data / "train" / f"{record['name']}.npz") as stored:
        return {k: np.asarray(stored[f"out_{k}"], dtype=np.float64) for k in OUTFLOW_KEYS}


def bulk_speed(data: Path, record: dict) -> np.ndarray:
    """Per sample of the run, the mass-weighted mean speed [m/s] of the cells more
    than ``BULK_DISTANCE`` from the feeder's centre (grid and feeder: the run's
    record)."""
    grid, feeder_x = record["grid"], float(record["dem_config"]["outlets"][0])
    with np.load(data / "train" / f"{record['name']}.npz") as stored:
        mass = np.asarray(stored["mass"], dtype=np.float64)
        velocity = np.asarray(stored["velocity"], dtype=np.float64)
    dx = (grid["x_max"] - grid["x_min"]) / grid["nx"]
    centres = grid["x_min"] + dx * (np.arange(grid["nx"]) + 0.5)
    away = np.abs(centres - feeder_x) > BULK_DISTANCE
    weight = mass[:, :, away].sum(axis=(1, 2))
    moved = (mass * np.hypot(velocity[..., 0], velocity[..., 1]))[:, :, away].sum(axis=(1, 2))
    return np.divide(moved, weight, out=np.zeros_like(moved), where=weight > 0)


def _start_time(data: Path, record: dict) -> float:
    """The simulated time [s] the run started at: its first sample's (``paper_design``
    samples the start state first; its start state need not ship)."""
    with np.load(data / "train" / f"{record['name']}.npz") as stored:
        return float(stored["time"][0])


def _cost(records: list) -> dict:
    duration = np.array([r["spec"]["duration"] for r in records], dtype=np.float64)
    wall = np.array([r["wall_s"] for r in records], dtype=np.float64) / duration
    cpu = np.array([r["cpu_s"] for r in records], dtype=np.float64) / duration
    return {"wall_s_per_simulated_s": float(wall.mean()),
            "cpu_s_per_simulated_s": float(cpu.mean()),
            "dt_s": float(records[0]["dt_s"]), "particles": int(records[0]["particles_start"])}


def _realisation(method_data: Path, run: dict, references: list, t0: float, t1: float,
                 window: float, explicit_discharged: float, explicit_bulk: list) -> dict:
    """One run of the method scored against every explicit replica: its errors, what
    its feeder delivered, and its bulk's speed (``jammed``, ``creeping``)."""
    outflow = _outflow(method_data, run)
    # the method's pile may have settled to a slightly different time: compare
    # the same seconds after each run's start
    outflow["time"] = outflow["time"] - _start_time(method_data, run) + t0
    scores = ensemble_score(outflow, references, t0, t1, window=window)
    discharged = float(run["discharged_mass_kg"])
    bulk = float(bulk_speed(method_data, run).mean())
    return {"run": run["name"],
            "tracking_error": scores["tracking_error"],
            "tracking_errors": scores["tracking_errors"],
            "grade_error": scores["grade_error"], "hardness_error": scores["hardness_error"],
            "discharged_kg": discharged,
            "jammed": bool(discharged < JAM_DELIVERED_SHARE * explicit_discharged),
            "bulk_speed_m_s": bulk,
            "creeping": bool(bulk > CREEP_FACTOR * max(explicit_bulk)),
            "mass_balance_error": float(run["mass_balance_error"]),
            # when the feeder last delivered: a jam shows as output stopping early
            "last_discharge_s": (float(outflow["time"].max()) - t0 if outflow["time"].size
                                 else 0.0)}


def score_dem_method(method_data, reference_data, window: float = metrics.WINDOW_S) -> dict:
    """Score the finished runs of ``method_data`` (an exported held-out design of
    another DEM method) against the explicit replicas in ``reference_data``, in
    ``window`` [s] windows (default 30 s; a shorter scene needs shorter ones).

    Returns ``{"method": ..., "scenes": {scene: {...}}, "failed": {scene: {...}}
    (runs the guard stopped: when, why, their cost so far, the picture at the
    failure), "skipped": {scene: why},
    "explicit_costs": {scene: {...}}}`` (the explicit replicas' cost in every
    reference scene, scored or not);
    raises ``ValidationError`` when no scene can be scored."""
    method_data, reference_data = Path(method_data), Path(reference_data)
    if not (isinstance(window, (int, float)) and 0.0 < window):
        raise ValidationError("window", "a number of seconds > 0", f"got {window!r}")
    method, reference = _done_runs(method_data), _done_runs(reference_data)
    scenes, skipped = {}, {}
    for scene, runs in method["scenes"].items():
        replicas = reference["scenes"].get(scene, [])
        if len(replicas) < 2:
            skipped[scene] = f"{len(replicas)} explicit replicas finished (2 needed)"
            continue
        references = [_outflow(reference_data, r) for r in replicas]
        t0 = _start_time(reference_data, replicas[0])
        t1 = t0 + float(replicas[0]["spec"]["duration"])
        if window > t1 - t0:
            raise ValidationError("window", f"at most the scene's {t1 - t0:g} s",
                                  f"got {window:g} s for {scene}")
        explicit_discharged = float(sum(r["discharged_mass_kg"] for r in replicas)
                                    / len(replicas))
        explicit_bulk = [float(bulk_speed(reference_data, r).mean()) for r in replicas]
        realisations = [_realisation(method_data, run, references, t0, t1, window,
                                     explicit_discharged, explicit_bulk) for run in runs]
        floor = noise_floor(references, t0, t1, window=window)
        scenes[scene] = {
            **{key: float(np.mean([r[key] for r in realisations]))
               for key in ("tracking_error", "grade_error", "hardness_error",
                           "discharged_kg", "bulk_speed_m_s")},
            # every realisation against every replica
            "tracking_error_spread": spread([e for r in realisations
                                              for e in r["tracking_errors"]]),
            "realisation_spread": spread([r["tracking_error"] for r in realisations]),
            "realisations": realisations,
            "tracking_error_dem_noise_floor": floor["tracking_error"],
            "dem_noise_floor_spread": floor["tracking_error_spread"],
            "method_cost": _cost(runs),
            "method_mass_balance_error": max(r["mass_balance_error"] for r in realisations),
            "explicit_discharged_kg": explicit_discharged,
            "explicit_bulk_speed_m_s": explicit_bulk,
            "jammed": any(r["jammed"] for r in realisations),
            "creeping": any(r["creeping"] for r in realisations),
            "last_discharge_s": min(r["last_discharge_s"] for r in realisations),
            "method_run": runs[0]["name"], "method_runs": [r["name"] for r in runs],
            "explicit_replicas": [r["name"] for r in replicas],
            "simulated_s": t1 - t0, "window_s": float(window)}
    failed = {}
    for scene, record in method["unstable"].items():
        if scene in scenes:
            continue
        after = record["unstable_dem_time_s"] - record["start_time_s"]
        failed[scene] = {"reason": record["unstable_reason"], "after_s": after,
                         "method_cost": _cost([dict(record, spec=dict(record["spec"],
                                                                      duration=after))]),
                         "picture": (str(method_data / record["failure_picture"])
                                     if record.get("failure_picture") else None)}
    if not scenes and not failed:
        why = "; ".join(f"{s}: {r}" for s, r in skipped.items()) or "no finished run"
        raise ValidationError("--data", "a finished run of a scene with 2 explicit replicas",
                              f"{method_data}: {why}")
    config = method["dem_config"]
    return {"method": config.get("method", "explicit"),
            "explicit_costs": {scene: _cost(replicas)
                               for scene, replicas in reference["scenes"].items()},
            "method_settings": {k: config[k] for k in ("nonsmooth_dt", "solver_iterations",
                                                       "solver_tolerance", "solver_relaxation",
                                                       "normal_stiffness")
                                if k in config},
            "method_design": method["design"], "reference_design": reference["design"],
            "scenes": scenes, "failed": failed, "skipped": skipped}
