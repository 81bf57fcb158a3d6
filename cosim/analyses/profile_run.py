"""One run of the quadratic-hardness scenario with the MWD survey, for the reproductions.

The scenario is ``examples/hardness_profile.toml`` (paper sections
"Identification of hardness from measurement-while-drilling" and
"Backtracking the grindability"). The run writes what ``minetwin simulate``
writes (``timeseries.parquet``, ``events.sqlite``, ``summary.json``; not
its overview plot) plus ``mwd.parquet``: the survey log (particle id ->
source, local origin x [m], MWD signal), because the event store keeps the
particles' intrinsic state only.

``--quick`` runs narrow the left face (8 m of advance per 15 t load instead
of 2 m), so the whole 100 m profile is mined in a quarter of the simulated
time, and shift the profile by a 20 m lead-in of hardness-1 ore, so the
mill's start-up (which the grindability analysis skips) is fed with ore from
before the first block.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from cosim import jsonio

SCENARIO = Path(__file__).resolve().parents[2] / "examples" / "hardness_profile.toml"
MWD_BETA = 0.4
"""True exponent of s = h**beta (paper)."""
MWD_LOCATION_ERROR_M = 12.5
"""Half-width of the uniform MWD location error [m] (paper)."""
QUICK_FACE_WIDTH_M = 0.25
"""Left face width of quick runs [m]: 8 m of advance per 15 t load."""
QUICK_LEAD_IN_M = 20.0
"""Hardness-1 ore ahead of the profile in quick runs [m] (two 10 m blocks)."""


@dataclass
class ProfileRun:
    """What a run leaves for the analyses."""

    config: dict
    timeseries: pd.DataFrame      # indexed by time [s]
    particles: pd.DataFrame       # EventStore.particles()
    survey: pd.DataFrame          # MwdSurvey.table()
    profiles: dict                # source name -> hardness profile h(x)
    run_summary: dict

    @property
    def times(self) -> np.ndarray:
        return self.timeseries.index.to_numpy(dtype=np.float64)

    @property
    def profile_start(self) -> float:
        """Where the left source's hardness profile starts [m] (local x)."""
        return float(self.config["assets"]["left"]["hardness"].get("start", 0.0))


def output_folder(out_dir) -> Path:
    """``out_dir`` created as a folder, or a ValidationError naming ``--out``."""
    from cosim.errors import ValidationError

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValidationError("--out", "a folder (created if missing)",
                              f"{str(out)!r} is a file")
    out.mkdir(parents=True, exist_ok=True)
    return out


def scenario_config(*, quick: bool, scenario=SCENARIO) -> dict:
    """The validated scenario, with the quick variant's narrower left face."""
    from cosim.scenario import load

    config = load(scenario)
    if quick:
        config = copy.deepcopy(config)
        left = config["assets"]["left"]
        left["face_width_m"] = QUICK_FACE_WIDTH_M
        left["hardness"]["start"] += QUICK_LEAD_IN_M
        left["hardness"]["end"] += QUICK_LEAD_IN_M
    return config


def run_profile(out_dir, *, until: float, config: dict, location_error: float =
                MWD_LOCATION_ERROR_M, seed: int | None = None, storage_model: str | None = None,
                progress: bool = False, probes=()) -> ProfileRun:
    """Build the scenario, add the MWD survey (and ``probes(simulation)`` components), run.

    ``probes`` is a sequence of callables taking the built ``Simulation``
    and returning a ``Component`` to add after the plant.
    """
    from cosim.analyses.mwd import MwdSurvey
    from cosim.scenario import build, summarize

    out = output_folder(out_dir)
    events_path = out / "events.sqlite"
    for suffix in ("", "-wal", "-shm"):
        Path(str(events_path) + suffix).unlink(missing_ok=True)
    simulation = build(config, seed=seed, storage_model=storage_model, events_path=events_path,
                       progress=progress)
    from cosim.scenario import assets_of_kind

    sources = {name: simulation.assets[name]
               for name in assets_of_kind(simulation.config, "source")}
    survey_seed = [simulation.config["simulation"]["seed"], 8]   # its own stream: the plant's
    survey = simulation.master.add(MwdSurvey(                      # draws stay unchanged
        simulation.plant.particles, sources, beta=MWD_BETA, location_error=location_error,
        rng=np.random.default_rng(survey_seed)))
    for probe in probes:
        simulation.master.add(probe(simulation))
    try:
        simulation.run(until)
    finally:
        simulation.close()
    # what `minetwin simulate` writes, less its overview plot (seconds per run)
    simulation.timeseries.to_parquet(out / "timeseries.parquet")
    run_summary = summarize(simulation)
    jsonio.write(out / "summary.json", run_summary, indent=2, sort_keys=True)
    survey.table().to_parquet(out / "mwd.parquet")
    (out / "scenario.json").write_text(json.dumps(simulation.config, indent=1) + "\n")
    return load_run(out, run_summary)


def load_run(run_dir, run_summary: dict | None = None) -> ProfileRun:
    """A finished run read back from its folder (for re-analysis without re-running)."""
    from cosim.blockmodel import hardness_function
    from cosim.events import EventStore

    run_dir = Path(run_dir)
    config = json.loads((run_dir / "scenario.json").read_text())
    with EventStore(run_dir / "events.sqlite") as events:
        particles = events.particles()
    if run_summary is None:
        run_summary = json.loads((run_dir / "summary.json").read_text())
    return ProfileRun(config=config, timeseries=pd.read_parquet(run_dir / "timeseries.parquet"),
                      particles=particles, survey=pd.read_parquet(run_dir / "mwd.parquet"),
                      profiles={name: hardness_function(table["hardness"])
                                for name, table in config["assets"].items()
                                if table["kind"] == "source"},
                      run_summary=run_summary)
