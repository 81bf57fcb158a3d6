"""Paper-scale DEM design of experiments for the stockpile ROM (issue 15).

Source: paper, sections "Simulator" (pseudo-particles of 0.2-0.48 m, 12-160
kg; the stockpile is 60 m tall) and "Integration test" (a stockpile of about
2,000 t in about 20,000 particles fed from the inlet, discharged by a feeder
at up to 2 t/s; the ROM trained "from groundtruth simulation data" over "the
relevant state-space [...] for in- and outflow"), and issue 15.

The stockpile (``paper_config``) is ``DemConfig``'s default, the paper's pile
in 2D: a 160 m floor with 3 m kerbs, the paper's two inlets 62 m above the
floor at x = -2 and +2 m (the container is about 60 m tall), one 8 m wide
feeder at x = 0 (the paper's tests use one outlet), disks of 0.2-0.48 m
(11-156 kg at 2700 kg/m^3; the paper's 12-160 kg) with k_n = 4e7 N/m.
Fields are sampled on a 2 m grid over the floor, 44 m high
(``paper_grid``: 80 x 22 cells, about 30 disks in a full cell).

Time step
---------
``STEP_FRACTION`` = 0.16: dt = 0.16 t_c = 189 us (t_c = 1.18 ms; the
default t_c/15 = 79 us). Measured with ``benchmarks/bench_dem_step.py`` on the
settled 20,000-disk base pile under the design's hardest load (feeder at
2 t/s and inflow at 2 t/s falling 29 m from the inlet), 4 s per step with the
blow-up guard every 0.05 s: see ``surrogate/rom/README.md`` ("Paper-scale
design") for the table. The step sits with a margin under the measured
limit, and every run keeps the guard (``doe.instability``, four checks per
control second) on: a run that blows up stops, is recorded as ``unstable``
and the design goes on. Measured (largest overlap / diameter, largest speed
of the settled bulk, particle-steps per CPU second): 0.16 t_c 4.0 %,
5.0 m/s, 7.5e6; 0.20 t_c 4.7 %, 5.5 m/s; 0.22 t_c 5.2 %, 10.9 m/s; 0.24
t_c 9.1 %, 17 m/s; 0.30 t_c 7.5 %, 30 m/s (faster than the 24 m/s impact
from the inlet); the guard trips at 0.34 t_c (after 0.30 s: a disk at
93 m/s) and within 0.05 s at 0.40 and 0.50 t_c. Up to 0.30 t_c it does not
trip within 4 s, but from 0.22 t_c on the overlaps and bulk speeds grow:
the onset of the instability, which 0.16 t_c stays 1.4x under (2.1x under
the blow-up).

Piles
-----
Pouring 2,000 t at 2 t/s would cost ~1,000 simulated seconds. The base piles
are instead laid out (``layered_pile``): disks packed in a 35 degree triangle
(``surrogate.dem.builders.packed_pile``'s layout) and assigned to 15 t lots
in nested chevron layers, ordered by ``y + |x| tan(35 deg)`` (the order in
which a pile fed from a point inlet above its crest buries its surface), with
the lots' entry times those of a pour at 2 t/s ending at t = 0; then the
pile settles for ``PileSpec.settle_time`` seconds (it slumps to about its
angle of repose). Derived states are DEM runs from these: a depleted pile
(crater over the feeder) is the end of a 2 t/s drain, a full pointy pile
the end of a 2 t/s fill, and piles built the way the integration test
builds them are fills from a partial pile with real inflow from the inlet.
A run's end state is a checkpoint the runs that start from it share.

Resumable and stored by content
-------------------------------
Every pile and run has a key: the SHA-256 of its inputs (DEM config, grid,
spec without its name, the key of its start state, seed, ``DESIGN_VERSION``
and the sampling constants). Layout of a work directory::

    design.json               the design and every key
    states/pile_<key>.npz     settled base piles (DEM checkpoints)
    states/run_<key>.npz      end state of a run (start of others)
    partial/<key>/ckpt_<k>.*  mid-run checkpoint after k control steps
    runs/<key>.npz            compact result (below)
    runs/<key>.json           record: inputs, seed, git commit, wall/CPU time,
                              particle-steps, mass balance, status
    manifest.json             all records (strict JSON)

A restarted design skips runs whose result exists (in the work directory or
in the committed data folder, ``--data``) and resumes a run from its latest
checkpoint, written every ``Design.checkpoint_interval`` simulated seconds;
the resumed run continues bit for bit (``Dem.save_checkpoint``, the lot
feed's generator state and the last ``VELOCITY_WINDOW`` seconds of bulk
snapshots are saved).

Compact result (``runs/<key>.npz``, compressed, float32 fields)
--------------------------------------------------------------
Per sample (one per ``CONTROL_STEP``, S = duration - VELOCITY_WINDOW + 1):
``time`` (S,) [s], ``mass`` (S, ny, nx) [kg], ``velocity`` (S, ny, nx, 2)
[m/s] (displacement over ``VELOCITY_WINDOW``), ``grade``, ``hardness``
(S, ny, nx) mass-weighted means (NaN where empty), ``discharge_rate`` (the
mass the feeder took that second) [kg/s], ``setpoint``, ``inflow_rate``
[kg/s], ``held_mass`` [kg], ``dispersion_fit`` (S, 2)
(``surrogate.rom.dispersion``); per discharged particle ``out_time`` [s],
``out_id``, ``out_tracking_id`` (uint64), ``out_mass`` [kg], ``out_grade``,
``out_hardness``. The sample keys are those of ``doe.load_samples``, so an
exported data folder trains with ``minetwin rom train --data DIR``.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import sys
import time
import dataclasses
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from cosim import batch
from surrogate.rom import doe
from surrogate.rom.dispersion import dispersion_fit
from surrogate.rom.grid import (Grid, displacement_velocity_field, mass_field,
                                mean_field)

DESIGN_VERSION = "paper-design-1"
"""Changes when the DEM physics or the sampling of this module changes (part of
every key, so results of another version are never reused)."""

STEP_FRACTION = 0.16
"""Time step over the contact time t_c [-] (module docstring, "Time step")."""

LAYOUT_ANGLE = 35.0
"""Slope [deg] of the laid-out base piles (they slump to about 30 degrees)."""

FILL_RATE = 2000.0
"""Rate [kg/s] of the pour whose entry times the laid-out lots get."""

DATA_DIR = Path(__file__).parent / "data" / "paper_design"
"""Committed compact results of the paper design."""

SAMPLE_KEYS = ("time", "mass", "velocity", "grade", "hardness", "discharge_rate", "setpoint",
               "inflow_rate", "held_mass", "dispersion_fit")
SNAPSHOT_KEYS = ("time", "id", "position", "mass", "grade", "hardness")


def paper_config(**overrides):
    """The paper-scale stockpile: ``DemConfig``'s defaults at ``STEP_FRACTION``."""
    from surrogate.dem import DemConfig

    values = dict(dt_safety_factor=1.0 / STEP_FRACTION)
    values.update(overrides)
    return DemConfig(**values)


def paper_grid(cfg, cell_size: float = 2.0, height: float = 44.0) -> Grid:
    """The ROM grid of the paper pile: the floor width x ``height`` [m] in
    ``cell_size`` [m] cells."""
    return doe.grid_of(cfg, cell_size=cell_size, height=height)


@dataclass(frozen=True)
class PileSpec:
    """A laid-out base pile: ``particles`` disks, generator ``seed``, settled
    for ``settle_time`` [s]."""

    name: str
    particles: int
    seed: int
    settle_time: float = 8.0


@dataclass(frozen=True)
class RunSpec:
    """One DEM run of the design under constant controls.

    Parameters
    ----------
    name : str
    start : str
        ``"pile:<name>"`` (a base pile) or ``"run:<name>"`` (another run's end).
    discharge_rate, inflow_rate : float
        Feeder and inflow rates [kg/s].
    duration : float
        Simulated seconds [s] (a whole number of ``CONTROL_STEP``).
    seed : int
        Seed of the lot feed (grades) of the inflow.
    first_tracking_id : int
        Tracking id of the run's first lot (blocks per run keep ids unique
        along a chain of runs).
    inlet : int
        Inlet the inflow enters at (0: x = -2 m).
    perturbation : float
        Every disk of the start state moved by this much [m] in a direction of
        its own (default 0: none), for replicas of a chaotic run.
    replica : int
        Which replica (seeds the directions; 0 with no perturbation).
    """

    name: str
    start: str
    discharge_rate: float
    inflow_rate: float
    duration: float
    seed: int
    first_tracking_id: int
    inlet: int = 0
    perturbation: float = 0.0
    replica: int = 0


@dataclass(frozen=True)
class Design:
    """A design: stockpile config, grid, base piles and runs in priority order."""

    name: str
    config: object
    grid: Grid
    piles: tuple
    runs: tuple
    checkpoint_interval: float = 20.0
    keep_start_states: bool = False
    """Export the runs' start states even once every run is done (a held-out
    design: the models scored on its runs start from them)."""
    changed: tuple = ()
    """``(field, value)`` pairs of DEM settings changed from the named design's
    (``with_settings``), for its ``regenerate`` command."""

    def pile(self, name: str) -> PileSpec:
        return next(p for p in self.piles if p.name == name)

    def run(self, name: str) -> RunSpec:
        return next(r for r in self.runs if r.name == name)


def _runs(rows) -> tuple:
    return tuple(RunSpec(name, start, q_out, q_in, duration, seed=k,
                         first_tracking_id=10_000 * (k + 1))
                 for k, (name, start, q_out, q_in, duration) in enumerate(rows))


def paper_design() -> Design:
    """The paper-scale design, most valuable runs first (``Design.runs`` order).

    Base piles: 20,000 disks (about 1.7 kt) and 14,300 (about 1.2 kt).
    Runs (discharge / inflow [kg/s], seconds): 150 s fill of the 1.2 kt
    pile at 2 t/s from the inlet (to about 1.5 kt, the integration test's
    pre-filled pile, built the way it builds it); the paper's throughputs 2
    and 1.2 t/s in and out (90 s); a 150 s fill of the 1.7 kt pile to about
    2 kt (full, pointy); a 200 s drain at 2 t/s to about 1.3 kt (depleted: a
    crater over the feeder); then 60 s runs from the full, the depleted and
    the inlet-built piles and from the base pile, spanning discharge 0-2 t/s
    and inflow 0-2 t/s.
    """
    cfg = paper_config()
    piles = (PileSpec("base_1700t", 20_000, seed=0), PileSpec("partial_1200t", 14_300, seed=1))
    rows = [
        ("fill_1200t_in2000", "pile:partial_1200t", 0.0, 2000.0, 150.0),
        ("base_out2000_in2000", "pile:base_1700t", 2000.0, 2000.0, 90.0),
        ("base_out1200_in1200", "pile:base_1700t", 1200.0, 1200.0, 90.0),
        ("fill_base_in2000", "pile:base_1700t", 0.0, 2000.0, 150.0),
        ("drain_base_out2000", "pile:base_1700t", 2000.0, 0.0, 200.0),
        ("filled_out1600_in1600", "run:fill_1200t_in2000", 1600.0, 1600.0, 60.0),
        ("full_out1500_in500", "run:fill_base_in2000", 1500.0, 500.0, 60.0),
        ("depleted_out1000_in2000", "run:drain_base_out2000", 1000.0, 2000.0, 60.0),
        ("depleted_out1200_in0", "run:drain_base_out2000", 1200.0, 0.0, 60.0),
        ("base_out500_in0", "pile:base_1700t", 500.0, 0.0, 60.0),
        ("base_out800_in1600", "pile:base_1700t", 800.0, 1600.0, 60.0),
        ("full_out2000_in2000", "run:fill_base_in2000", 2000.0, 2000.0, 60.0),
        ("depleted_out300_in300", "run:drain_base_out2000", 300.0, 300.0, 60.0),
        ("filled_out2000_in0", "run:fill_1200t_in2000", 2000.0, 0.0, 60.0),
    ]
    return Design("paper", cfg, paper_grid(cfg), piles, _runs(rows), checkpoint_interval=20.0)


def reduced_design() -> Design:
    """The paper geometry, grid and chain of states on a few hundred disks and
    seconds (for tests): a base pile, a drain, a fill and a run from the
    drained pile."""
    cfg = paper_config()
    piles = (PileSpec("base_small", 300, seed=0, settle_time=2.0),)
    rows = [
        ("small_out1000_in1000", "pile:base_small", 1000.0, 1000.0, 7.0),
        ("small_drain_out1500", "pile:base_small", 1500.0, 0.0, 6.0),
        ("small_depleted_out500_in1500", "run:small_drain_out1500", 500.0, 1500.0, 6.0),
    ]
    return Design("reduced", cfg, paper_grid(cfg), piles, _runs(rows), checkpoint_interval=2.0)


HELDOUT_PERTURBATION = 1e-6
"""Start-state perturbation [m] of the held-out replicas after the first."""

HELDOUT_REPLICAS = 3
"""DEM replicas per held-out scene (issue 15: at least 3)."""


def _heldout_runs(start: str, scenes, duration: float, first_seed: int,
                  replicas: int = HELDOUT_REPLICAS) -> tuple:
    """Each scene ``(name, discharge, inflow)`` as ``replicas`` runs of
    the same inflow (same feed seed and tracking ids) from ``start``, the
    first unperturbed, the others moved by ``HELDOUT_PERTURBATION``; ordered
    replica by replica, so that every scene gets its first two (a noise floor)
    before any gets its third."""
    runs = []
    for replica in range(replicas):
        for k, (name, q_out, q_in) in enumerate(scenes):
            runs.append(RunSpec(f"{name}_r{replica}", start, q_out, q_in, duration,
                                seed=first_seed + k, first_tracking_id=10_000 * (first_seed + k),
                                perturbation=HELDOUT_PERTURBATION if replica else 0.0,
                                replica=replica))
    return tuple(runs)


HELDOUT_SCENES = (("heldout_q1200", 1200.0, 1200.0), ("heldout_q2000", 2000.0, 2000.0),
                  ("heldout_out1500_in700", 1500.0, 700.0))
"""The held-out scenes ``(name, discharge [kg/s], inflow [kg/s])``."""


HELDOUT_PILE = PileSpec("heldout_1500t", 17_500, seed=2)
"""The held-out scenes' laid-out pile (about 1.5 kt), for every method and stiffness."""


def paper_heldout_design() -> Design:
    """Held-out paper-scale scenes for scoring the ROM (issue 15): a laid-out
    pile of 17,500 disks (about 1.5 kt, the integration test's pre-filled
    state; the design's laid-out piles hold 1.2 and 1.7 kt) run for 180 s at
    the paper's throughputs, 1.2 and 2 t/s in and out, and draining at
    1.5 t/s with 0.7 t/s in (a rate pair not in the design), each as
    ``HELDOUT_REPLICAS`` DEM replicas."""
    cfg = paper_config()
    piles = (HELDOUT_PILE,)
    return Design("paper_heldout", cfg, paper_grid(cfg), piles,
                  _heldout_runs(f"pile:{HELDOUT_PILE.name}", HELDOUT_SCENES, 180.0, first_seed=100),
                  checkpoint_interval=20.0, keep_start_states=True)


def paper_heldout_nonsmooth_design() -> Design:
    """The held-out scenes of ``paper_heldout_design`` run by the nonsmooth DEM
    (``DemConfig(method="nonsmooth")``: the paper's 11 ms step and 100 projected
    Gauss-Seidel sweeps, Servin et al. 2014), one run per scene, to score that
    method's tracking error against the explicit DEM's replicas at the paper's
    scale (``surrogate.rom.evaluate.score_dem_method``). Its pile is laid out as
    the explicit design's (same disks and seed) and settled by the nonsmooth
    method."""
    cfg = paper_config(method="nonsmooth")
    piles = (HELDOUT_PILE,)
    return Design("paper_heldout_nonsmooth", cfg, paper_grid(cfg), piles,
                  _heldout_runs(f"pile:{HELDOUT_PILE.name}", HELDOUT_SCENES, 180.0, first_seed=100,
                                replicas=1),
                  checkpoint_interval=20.0)


ROCK_STIFFNESS = 1.0e10
"""Per-contact normal stiffness [N/m] of granite: E = 50 GPa, nu = 0.25,
E* = E / (2 (1 - nu^2)) = 26.7 GPa, k_n ~ E* d with the mean diameter 0.376 m
(``surrogate/dem/README.md``); 250 times ``DemConfig``'s default, a contact time
16 times shorter."""

ROCK_SCENES = (("rock_out2000", 2000.0, 0.0),)
"""The rock-stiffness scene: the held-out 1.5 kt pile drained at 2 t/s (no inflow)."""

ROCK_INFLOW_SCENES = (("rock_out2000_in2000", 2000.0, 2000.0),)
"""The rock-stiffness inflow scene: the held-out pile drained at 2 t/s while the
inlet feeds 2 t/s onto it (the paper's throughput, falling about 30 m)."""

ROCK_DURATION = 20.0
"""Simulated seconds [s] of the rock scene: at 1e10 N/m the explicit DEM's step is
16 times shorter, so a 180 s replica would cost about 10 CPU hours."""


def _rock_design(name: str, replicas: int, scenes=ROCK_SCENES, first_seed: int = 200,
                 **settings) -> Design:
    """The held-out pile at ``ROCK_STIFFNESS`` run through ``scenes`` for
    ``ROCK_DURATION`` s, ``replicas`` runs each, with the DEM ``settings``."""
    cfg = paper_config(normal_stiffness=ROCK_STIFFNESS, **settings)
    return Design(name, cfg, paper_grid(cfg), (HELDOUT_PILE,),
                  _heldout_runs(f"pile:{HELDOUT_PILE.name}", scenes, ROCK_DURATION,
                                first_seed=first_seed, replicas=replicas),
                  checkpoint_interval=10.0)


def paper_rock_design() -> Design:
    """The held-out 1.5 kt pile (17,500 disks) at the rock stiffness
    ``ROCK_STIFFNESS``, drained at the paper's 2 t/s for ``ROCK_DURATION`` s by the
    explicit DEM at ``STEP_FRACTION`` of its contact time, ``HELDOUT_REPLICAS``
    replicas: the reference and noise floor the nonsmooth method is scored
    against where the explicit step collapses (issue 22)."""
    return _rock_design("paper_rock", HELDOUT_REPLICAS)


def paper_rock_nonsmooth_design() -> Design:
    """``paper_rock_design``'s scene by the nonsmooth DEM at the paper's 11 ms and
    100 sweeps (Servin et al. 2014), its pile laid out alike and settled by that
    method; ``HELDOUT_REPLICAS`` realisations, as the explicit DEM's (the method
    is chaotic too, so one run says little about its error)."""
    return _rock_design("paper_rock_nonsmooth", HELDOUT_REPLICAS, method="nonsmooth")


def paper_rock_inflow_design() -> Design:
    """``paper_rock_design``'s pile and method with ``ROCK_INFLOW_SCENES``: fed
    2 t/s from the inlet while drained at 2 t/s, ``HELDOUT_REPLICAS`` explicit
    replicas (the reference where falling disks hit the pile at rock stiffness)."""
    return _rock_design("paper_rock_inflow", HELDOUT_REPLICAS, ROCK_INFLOW_SCENES, first_seed=210)


def paper_rock_inflow_nonsmooth_design() -> Design:
    """``paper_rock_inflow_design``'s scene by the nonsmooth DEM at the paper's
    11 ms and 100 sweeps (Servin et al. 2014), ``HELDOUT_REPLICAS`` realisations."""
    return _rock_design("paper_rock_inflow_nonsmooth", HELDOUT_REPLICAS, ROCK_INFLOW_SCENES,
                        first_seed=210,
                        method="nonsmooth")


VALIDATION_REPLICAS = 3
"""DEM replicas of each validation scene: a reference and two more, so that its score and
noise floor are means over an ensemble (as the held-out scenes')."""

VALIDATION_SCENES = (("validation_q1600", 1600.0, 1600.0),)
"""The validation scene ``(name, discharge [kg/s], inflow [kg/s])``: between the
paper's two throughputs, a rate pair neither the design nor the held-out scenes run."""

VALIDATION_PILE = PileSpec("validation_1600t", 19_000, seed=3)
"""The validation scene's laid-out pile (about 1.6 kt, between the design's 1.2 and
1.7 kt and beside the held-out scenes' 1.5 kt)."""


def _validation_design(name: str, pile: PileSpec, scenes, duration: float,
                       first_seed: int) -> Design:
    """A validation design: ``scenes`` run for ``duration`` [s] from the laid-out
    ``pile``, each as ``VALIDATION_REPLICAS`` DEM replicas (``_heldout_runs``)."""
    cfg = paper_config()
    return Design(name, cfg, paper_grid(cfg), (pile,),
                  _heldout_runs(f"pile:{pile.name}", scenes, duration, first_seed=first_seed,
                                replicas=VALIDATION_REPLICAS),
                  checkpoint_interval=20.0, keep_start_states=True)


def paper_validation_design() -> Design:
    """A validation scene for choosing among fitted models by tracking (``rom train
    --validation``), apart from both the design they are fitted on and the held-out
    scenes they are scored on (a train / validation / test split): a laid-out pile
    of 19,000 disks (about 1.6 kt) run for 180 s at 1.6 t/s in and out, as
    ``VALIDATION_REPLICAS`` DEM replicas."""
    return _validation_design("paper_validation", VALIDATION_PILE, VALIDATION_SCENES, 180.0,
                              first_seed=300)


VALIDATION_DRAIN_SCENES = (("validation_out2000_in300", 2000.0, 300.0),)
"""The draining validation scene ``(name, discharge [kg/s], inflow [kg/s])``: the
rates of the depleted phase of ``surrogate.rom.pile_states``, where a ROM that
leaves its bulk hanging over emptied cells shows it (``surrogate.rom.hanging``)."""

VALIDATION_DRAIN_DURATION = 210.0
"""Simulated seconds [s] of the draining validation scene: it takes the 1.6 kt
pile down to about 1.23 kt, just above the design's lightest pile (1.2 kt)."""


def paper_validation_drain_design() -> Design:
    """A second validation scene, draining: ``paper_validation_design``'s pile (the
    same laid-out 19,000 disks, so the same settled start) drained at 2 t/s with
    0.3 t/s of inflow for ``VALIDATION_DRAIN_DURATION`` s, as
    ``VALIDATION_REPLICAS`` DEM replicas. Where the first validation scene holds
    its mass, this one tests what a model does to a pile it empties."""
    return _validation_design("paper_validation_drain", VALIDATION_PILE,
                              VALIDATION_DRAIN_SCENES, VALIDATION_DRAIN_DURATION,
                              first_seed=310)


VALIDATION_Q2000_SCENES = (("validation_q2000", 2000.0, 2000.0),)
"""The validation scene at the paper's top throughput ``(name, discharge [kg/s],
inflow [kg/s])``: 2 t/s in and out, on a pile (1.6 kt) neither the design nor the
held-out scenes run at that rate pair."""


def paper_validation_q2000_design() -> Design:
    """A third validation scene, at the paper's 2 t/s in and out:
    ``paper_validation_design``'s pile (the same laid-out 19,000 disks, so the same
    settled start) for 180 s, as ``VALIDATION_REPLICAS`` DEM replicas. The other two
    run 1.6 t/s and a drain; fits they cannot tell apart can track 2 t/s very
    differently (surrogate/rom/README.md, "Three validation scenes")."""
    return _validation_design("paper_validation_q2000", VALIDATION_PILE,
                              VALIDATION_Q2000_SCENES, 180.0, first_seed=320)


VALIDATION_Q2000_B_PILE = PileSpec("validation_b_1500t", 17_500, seed=4)
"""The second 2 t/s validation scene's laid-out pile: as many disks as the held-out
pile (about 1.5 kt) poured with another seed, so a pile of another shape."""

VALIDATION_Q2000_B_SCENES = (("validation_b_q2000", 2000.0, 2000.0),)
"""The second validation scene at 2 t/s in and out ``(name, discharge [kg/s], inflow
[kg/s])``."""


def paper_validation_q2000_b_design() -> Design:
    """A fourth validation scene, 2 t/s in and out for 180 s on a pile of its own
    (``VALIDATION_Q2000_B_PILE``), as ``VALIDATION_REPLICAS`` DEM replicas. With one
    pile, fits that track the validation pile's 2 t/s scene alike can track another
    pile's very differently (surrogate/rom/README.md, "A second pile at 2 t/s")."""
    return _validation_design("paper_validation_q2000_b", VALIDATION_Q2000_B_PILE,
                              VALIDATION_Q2000_B_SCENES, 180.0, first_seed=330)


def reduced_heldout_design() -> Design:
    """``paper_heldout_design`` on a few hundred disks and seconds (for tests)."""
    cfg = paper_config()
    piles = (PileSpec("heldout_small", 300, seed=2, settle_time=2.0),)
    scenes = (("small_heldout_q1000", 1000.0, 1000.0),)
    return Design("reduced_heldout", cfg, paper_grid(cfg), piles,
                  _heldout_runs("pile:heldout_small", scenes, 8.0, first_seed=100),
                  checkpoint_interval=2.0, keep_start_states=True)


DESIGNS = {"paper": paper_design, "reduced": reduced_design,
           "paper_heldout": paper_heldout_design, "reduced_heldout": reduced_heldout_design,
           "paper_heldout_nonsmooth": paper_heldout_nonsmooth_design,
           "paper_validation": paper_validation_design,
           "paper_validation_drain": paper_validation_drain_design,
           "paper_validation_q2000": paper_validation_q2000_design,
           "paper_validation_q2000_b": paper_validation_q2000_b_design,
           "paper_rock": paper_rock_design, "paper_rock_nonsmooth": paper_rock_nonsmooth_design,
           "paper_rock_inflow": paper_rock_inflow_design,
           "paper_rock_inflow_nonsmooth": paper_rock_inflow_nonsmooth_design}


def with_settings(design: Design, changes: dict) -> Design:
    """``design`` with the DEM settings ``changes`` ({DemConfig field: value}),
    e.g. more solver sweeps for a nonsmooth design: every key changes with them,
    so its runs are stored beside the named design's, never in their place."""
    if not changes:
        return design
    config = type(design.config).from_dict({**design.config.to_dict(), **changes})
    merged = {**dict(design.changed), **changes}
    return dataclasses.replace(design, config=config, changed=tuple(sorted(merged.items())))


def only_runs(design: Design, names) -> Design:
    """``design`` reduced to the runs ``names`` (and the runs they start from, so
    a chain still runs in order); their keys are the whole design's."""
    from cosim.errors import ValidationError

    known = [r.name for r in design.runs]
    wanted = set(names)
    unknown = sorted(wanted - set(known))
    if unknown:
        raise ValidationError("--only", f"runs of {design.name}: {', '.join(known)}",
                              f"got {', '.join(unknown)}")
    for run in reversed(design.runs):  # add each wanted run's start run
        kind, _, start = run.start.partition(":")
        if run.name in wanted and kind == "run":
            wanted.add(start)
    return dataclasses.replace(design, runs=tuple(r for r in design.runs if r.name in wanted))


def get_design(name: str) -> Design:
    if name not in DESIGNS:
        from cosim.errors import ValidationError

        raise ValidationError("--design", f"one of {sorted(DESIGNS)}", f"got {name!r}")
    return DESIGNS[name]()


# ------------------------------------------------------------------- keys
def _digest(payload: dict) -> str:
    text = json.dumps(payload, sort_keys=True, allow_nan=False, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


SETTINGS_SINCE_VERSION_1 = ("beverloo_c", "beverloo_k", "method", "nonsmooth_dt",
                            "solver_iterations", "solver_tolerance", "stabilization_steps",
                            "impact_speed", "guard_speed_factor", "guard_energy_growth",
                            "guard_overlap_ratio", "missed_contact_resolves",
                            "solver_relaxation")
"""DEM settings added after the design's runs began (the nonsmooth method, the
feeder's Beverloo bound, the blow-up guard). They enter a key only when they
differ from their defaults, with which a run is the explicit DEM it was before
they existed (the paper's feeder rates stay far below the orifice's capacity;
the guard only stops a run that blows up), so finished runs keep their keys."""
UNKEYED_SETTINGS = ("threads",)
"""Settings that do not change a result (the kernels are bitwise equal for any
thread count)."""


def _keyed_config(config) -> dict:
    defaults = type(config)().to_dict()
    return {k: v for k, v in config.to_dict().items() if k not in UNKEYED_SETTINGS
            and (k not in SETTINGS_SINCE_VERSION_1 or v != defaults[k])}


NONSMOOTH_REVISION = 2
"""Revision of the nonsmooth solver, in the keys of nonsmooth runs only: revision 2
checks for contacts missed before the solve (``surrogate.dem.nonsmooth``, item 6).
Revision 1's runs of ``paper_heldout_nonsmooth`` blew up under the inflow (their
records stay in git history); revision 2's run again under new keys."""


def _common(design: Design) -> dict:
    common = {"design_version": DESIGN_VERSION, "config": _keyed_config(design.config),
              "grid": design.grid.to_dict(), "control_step": doe.CONTROL_STEP,
              "velocity_window": doe.VELOCITY_WINDOW, "bulk_age": doe.BULK_AGE,
              "lot_mass": doe.LOT_MASS, "layout_angle": LAYOUT_ANGLE, "fill_rate": FILL_RATE}
    if design.config.method == "nonsmooth":
        common["nonsmooth_revision"] = NONSMOOTH_REVISION
    return common


def pile_key(design: Design, pile: PileSpec) -> str:
    """Content key of a base pile (its name plays no part)."""
    spec = {k: v for k, v in asdict(pile).items() if k != "name"}
    return _digest({**_common(design), "kind": "pile", "spec": spec})


def start_key(design: Design, start: str) -> str:
    """Key of the state ``start`` (``pile:<name>`` or ``run:<name>``)."""
    kind, _, name = start.partition(":")
    if kind == "pile":
        return "pile_" + pile_key(design, design.pile(name))
    if kind == "run":
        return "run_" + run_key(design, design.run(name))
    from cosim.errors import ValidationError

    raise ValidationError("start", "'pile:<name>' or 'run:<name>'", f"got {start!r}")


REPLICA_FIELDS = ("perturbation", "replica")
"""Run fields added after the design's runs began: they enter a key only when a
run is a perturbed replica, so the unperturbed runs keep their keys."""


def run_key(design: Design, run: RunSpec) -> str:
    """Content key of a run: its inputs and its start state's key, not its name."""
    spec = {k: v for k, v in asdict(run).items() if k not in ("name", "start")}
    if not run.perturbation:
        spec = {k: v for k, v in spec.items() if k not in REPLICA_FIELDS}
    return _digest({**_common(design), "kind": "run", "spec": spec,
                    "start": start_key(design, run.start)})


# ------------------------------------------------------------------ piles
def emit_feed(dem, feed: doe.LotFeed, mass: float, inlet: int = 0) -> None:
    """Emit ``mass`` [kg] of the feed's current lot(s) at ``inlet``."""
    for piece, tid, grade, hardness in feed.take(mass):
        dem.emit(piece, grade, hardness, doe.FEED_F, tid, inlet=inlet)


def layered_pile(cfg, particles: int, seed: int):
    """A ``Dem`` holding ``particles`` disks at rest in a ``LAYOUT_ANGLE``
    triangle, in 15 t lots laid as nested chevrons (module docstring,
    "Piles"): tracking ids 1, 2, ... from the core outwards, hardness
    alternating 1 and 2, grades uniform in [0.2, 0.8], the size distribution
    ``doe.FEED_F``, entry times of a ``FILL_RATE`` pour ending at t = 0."""
    from surrogate.dem import Dem
    from surrogate.dem.builders import packed_pile

    layout = packed_pile(cfg, particles, seed=seed, angle_deg=LAYOUT_ANGLE)
    position = layout.pos
    mass = cfg.sphere_mass(2.0 * layout.radius)
    burial = position[:, 1] + np.abs(position[:, 0]) * math.tan(math.radians(LAYOUT_ANGLE))
    order = np.argsort(burial, kind="stable")
    position, mass = position[order], mass[order]
    before = np.cumsum(mass) - mass  # mass laid before each disk
    lot = (before // doe.LOT_MASS).astype(np.int64)
    rng = np.random.default_rng(seed)
    lot_grade = rng.uniform(0.2, 0.8, int(lot.max()) + 1)
    tracking_id = (lot + 1).astype(np.uint64)
    dem = Dem(cfg, seed=seed)
    dem.place(position, mass, lot_grade[lot], 1.0 + (tracking_id % 2), doe.FEED_F, tracking_id)
    lot_start = lot * doe.LOT_MASS
    dem.entry_time = (lot_start - mass.sum()) / FILL_RATE
    return dem


def build_pile(design: Design, pile: PileSpec, progress=None):
    """Lay out and settle ``pile``; returns ``(dem, record)`` (the record has
    the pile's bulk areal density [kg/m^2] and angle of repose [rad],
    measured as ``doe`` does, for the ROM's container)."""
    tic, cpu0 = time.perf_counter(), time.process_time()
    dem = layered_pile(design.config, pile.particles, pile.seed)
    particle_steps = 0.0
    steps = int(round(pile.settle_time / doe.CONTROL_STEP))
    for k in range(steps):
        before = dem.steps_done
        reason = doe.advance_guarded(dem, doe.CONTROL_STEP)
        particle_steps += (dem.steps_done - before) * dem.n
        if reason:
            from cosim.errors import ValidationError

            raise ValidationError("pile", "a stable settling run",
                                  f"{pile.name} blew up at t = {dem.time:.2f} s: {reason}")
        if progress:
            progress(tqdm.format_meter(k + 1, steps, time.perf_counter() - tic,
                                       prefix=f"pile {pile.name}: settling", unit="sim-s",
                                       ascii=True))
    snapshot = dem.snapshot()
    record = {"kind": "pile", "name": pile.name, "spec": asdict(pile),
              "particles": dem.n, "held_mass_kg": dem.held_mass(),
              "areal_density_kg_m2": doe.areal_density(snapshot, design.grid),
              "repose_angle_rad": doe.repose_angle(snapshot),
              "max_overlap_over_diameter": dem.max_overlap_ratio(),
              "wall_s": time.perf_counter() - tic, "cpu_s": time.process_time() - cpu0,
              "particle_steps": particle_steps, "dt_s": dem.dt,
              "dt_over_tc": dem.dt / design.config.contact_time}
    return dem, record


# ------------------------------------------------------------------- runs
def _bulk(dem) -> dict:
    snapshot = doe.bulk_only(dem.snapshot())
    return {k: snapshot[k] for k in SNAPSHOT_KEYS}


def _sample(grid: Grid, before: dict, after: dict, taken: float, run: RunSpec,
            held: float) -> dict:
    position, mass = before["position"], before["mass"]
    return {"time": float(before["time"]), "mass": mass_field(grid, position, mass),
            "velocity": displacement_velocity_field(grid, before, after),
            "grade": mean_field(grid, position, mass, before["grade"]),
            "hardness": mean_field(grid, position, mass, before["hardness"]),
            "discharge_rate": taken, "setpoint": run.discharge_rate,
            "inflow_rate": run.inflow_rate, "held_mass": held,
            "dispersion_fit": dispersion_fit(grid, before, after)}


class _RunState:
    """What a run carries from one control step to the next (saved with each
    checkpoint): samples so far, the feeder's take per step, the outflow, the
    last bulk snapshots, the lot feed and the cost counters."""

    def __init__(self, run: RunSpec):
        self.step = 0
        self.samples = {k: [] for k in SAMPLE_KEYS}
        self.taken, self.held, self.window = [], [], []
        self.outflow = []
        self.inflow = []
        self.feed = doe.LotFeed(run.first_tracking_id, run.seed)
        self.wall = self.cpu = self.particle_steps = 0.0
        self.resumed_at = []
        self.start = {}  # particles, held and emitted mass [kg], time [s] of the start state

    def save(self, path: Path) -> None:
        # float32 as in the result: the cast is the same whenever it happens
        arrays = {f"sample_{k}": np.array(v, dtype=np.float32) for k, v in self.samples.items()}
        arrays.update({f"window{i}_{k}": np.asarray(s[k]) for i, s in enumerate(self.window)
                       for k in SNAPSHOT_KEYS})
        outflow = _join_outflow(self.outflow)
        arrays.update({f"out_{k}": v for k, v in outflow.items()})
        arrays.update({f"in_{k}": v for k, v in _join_outflow(self.inflow).items()})
        feed = {"rng": self.feed.rng.bit_generator.state, "tracking_id": self.feed.tracking_id,
                "left": self.feed.left, "grade": self.feed.grade,
                "hardness": self.feed.hardness}
        meta = {"step": self.step, "taken": self.taken, "held": self.held,
                "window": len(self.window), "feed": feed, "wall": self.wall, "cpu": self.cpu,
                "particle_steps": self.particle_steps, "resumed_at": self.resumed_at,
                "samples": len(self.samples["time"]), "start": self.start}
        with open(path, "wb") as handle:
            np.savez_compressed(handle, meta=np.array(json.dumps(meta)), **arrays)

    @classmethod
    def load(cls, path: Path, run: RunSpec) -> "_RunState":
        state = cls(run)
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            state.step, state.taken, state.held = meta["step"], meta["taken"], meta["held"]
            count = meta["samples"]
            state.samples = {k: list(data[f"sample_{k}"]) if count else []
                             for k in SAMPLE_KEYS}
            state.window = [{k: data[f"window{i}_{k}"].copy() for k in SNAPSHOT_KEYS}
                            for i in range(meta["window"])]
            for s in state.window:
                s["time"] = float(s["time"])
            state.outflow = [{k: data[f"out_{k}"].copy() for k in _OUTFLOW_KEYS}]
            if "in_id" in data.files:
                state.inflow = [{k: data[f"in_{k}"].copy() for k in _OUTFLOW_KEYS}]
            feed = meta["feed"]
            state.feed.rng.bit_generator.state = feed["rng"]
            state.feed.tracking_id, state.feed.left = feed["tracking_id"], feed["left"]
            state.feed.grade, state.feed.hardness = feed["grade"], feed["hardness"]
            state.wall, state.cpu = meta["wall"], meta["cpu"]
            state.particle_steps, state.resumed_at = meta["particle_steps"], meta["resumed_at"]
            state.start = meta.get("start", {})
        return state


_OUTFLOW_KEYS = ("time", "id", "tracking_id", "mass", "grade", "hardness")


def _join_outflow(records: list) -> dict:
    if not records:
        return {"time": np.empty(0), "id": np.empty(0, np.uint64),
                "tracking_id": np.empty(0, np.uint64), "mass": np.empty(0),
                "grade": np.empty(0), "hardness": np.empty(0)}
    return {k: np.concatenate([np.asarray(r[k]) for r in records]) for k in _OUTFLOW_KEYS}


def _checkpoint(directory: Path, dem, state: _RunState) -> None:
    """``ckpt_<step>.dem.npz`` then ``ckpt_<step>.run.npz`` (written last: a
    checkpoint counts only when both exist); older ones are removed after."""
    directory.mkdir(parents=True, exist_ok=True)
    base = directory / f"ckpt_{state.step:06d}"
    for suffix, write in ((".dem.npz", dem.save_checkpoint), (".run.npz", state.save)):
        tmp = base.with_name(base.name + suffix + ".tmp")
        write(tmp)
        os.replace(tmp, base.with_name(base.name + suffix))
    for old in directory.glob("ckpt_*"):
        if not old.name.startswith(base.name):
            old.unlink(missing_ok=True)


def latest_checkpoint(directory: Path):
    """``(dem_path, run_path)`` of the latest complete checkpoint, or None."""
    done = sorted(directory.glob("ckpt_*.run.npz")) if directory.is_dir() else []
    for run_path in reversed(done):
        dem_path = run_path.with_name(run_path.name.replace(".run.npz", ".dem.npz"))
        if dem_path.is_file():
            return dem_path, run_path
    return None


CHECKPOINT_WALL_S = 600.0
"""A run also writes a checkpoint after this much wall time [s] since its
last one (a slow, shared machine reaches ``Design.checkpoint_interval``
simulated seconds only after a long while)."""


def run_one(design: Design, run: RunSpec, work: Path, start_path: Path, progress=None,
            progress_every: float = 60.0, data: Path | None = None) -> dict:
    """Run ``run`` from the state in ``start_path`` (or resume it from its
    latest checkpoint in ``work/partial/<key>``, else in the data folder's
    ``partial/<key>``); write its compact result, end state and record;
    return the record."""
    from surrogate.dem import Dem

    key = run_key(design, run)
    partial = work / "partial" / key
    latest = latest_checkpoint(partial)
    committed = None if data is None else latest_checkpoint(Path(data) / "partial" / key)
    if latest is None and committed is not None:
        partial.mkdir(parents=True, exist_ok=True)
        for path in committed:
            shutil.copyfile(path, partial / path.name)
        latest = latest_checkpoint(partial)
    if latest:
        dem = Dem.load_checkpoint(latest[0])
        state = _RunState.load(latest[1], run)
        state.resumed_at.append(state.step * doe.CONTROL_STEP)
        _say(progress, f"run {run.name} ({key}): resuming at t = {state.step} s")
    else:
        dem = Dem.load_checkpoint(start_path)
        state = _RunState(run)
        if run.perturbation:
            perturb(dem, run)
        dem.discharged()  # flush: only this run's outflow is recorded
        state.window = [_bulk(dem)]
        state.held = [dem.held_mass()]
        state.start = {"particles": dem.n, "held_mass_kg": dem.held_mass(), "time_s": dem.time,
                       "emitted_mass_kg": dem.emitted_mass,
                       "discharged_mass_kg": dem.discharged_mass}
    dem.set_discharge_rate(run.discharge_rate, outlet=0)
    steps = int(round(run.duration / doe.CONTROL_STEP))
    lag = max(int(round(doe.VELOCITY_WINDOW / doe.CONTROL_STEP)), 1)
    every = max(int(round(design.checkpoint_interval / doe.CONTROL_STEP)), 1)
    last_report = last_checkpoint = time.perf_counter()
    reason = None
    while state.step < steps:
        tic, cpu0 = time.perf_counter(), time.process_time()
        if run.inflow_rate > 0:
            first_new = dem.n
            emit_feed(dem, state.feed, run.inflow_rate * doe.CONTROL_STEP, inlet=run.inlet)
            # every model scored on a held-out run is fed these very particles
            state.inflow.append({"time": np.full(dem.n - first_new, dem.time),
                                 **{k: getattr(dem, k)[first_new:].copy()
                                    for k in _OUTFLOW_KEYS if k != "time"}})
        n_before, steps_before = dem.n, dem.steps_done
        reason = doe.advance_guarded(dem, doe.CONTROL_STEP)
        state.particle_steps += (dem.steps_done - steps_before) * n_before
        if reason:
            break
        out = dem.discharged()
        state.outflow.append({k: out[k] for k in _OUTFLOW_KEYS})
        state.taken.append(float(out["mass"].sum()) / doe.CONTROL_STEP)
        state.window.append(_bulk(dem))
        state.held.append(dem.held_mass())
        if len(state.window) > lag:
            j = len(state.samples["time"])
            sample = _sample(design.grid, state.window[0], state.window[lag], state.taken[j],
                             run, state.held[j])
            for k, v in sample.items():
                state.samples[k].append(v)
            state.window.pop(0)
        state.step += 1
        state.wall += time.perf_counter() - tic
        state.cpu += time.process_time() - cpu0
        due = time.perf_counter() - last_checkpoint >= CHECKPOINT_WALL_S
        if (state.step % every == 0 or due) and state.step < steps:
            _checkpoint(partial, dem, state)
            last_checkpoint = time.perf_counter()
        if progress and time.perf_counter() - last_report >= progress_every:
            last_report = time.perf_counter()
            left = (steps - state.step) * dem.n / dem.dt * doe.CONTROL_STEP
            cpu_rate = state.particle_steps / max(state.cpu, 1e-9)
            wall_rate = state.particle_steps / max(state.wall, 1e-9)
            _say(progress, tqdm.format_meter(
                state.step, steps, state.wall, prefix=f"run {run.name}", unit="sim-s",
                ascii=True, rate=state.step / max(state.wall, 1e-9),
                postfix=f"{dem.n} disks, held {dem.held_mass() / 1e3:.0f} t, "
                        f"{cpu_rate / 1e6:.1f}e6 particle-steps per CPU s "
                        f"({wall_rate / 1e6:.1f}e6 per wall s), "
                        f"{_duration(left / cpu_rate)} of CPU left"))
    record = {"kind": "run", "name": run.name, "key": key, "design": design.name,
              "design_version": DESIGN_VERSION, "spec": asdict(run),
              "start_key": start_key(design, run.start), "seed": run.seed,
              "git_commit": batch.code_version(), "dem_config": design.config.to_dict(),
              "grid": design.grid.to_dict(), "dt_s": dem.dt,
              "dt_over_tc": dem.dt / design.config.contact_time,
              "wall_s": state.wall, "cpu_s": state.cpu,
              "particle_steps": state.particle_steps, "resumed_at_s": state.resumed_at,
              "start_time_s": state.start.get("time_s"),
              "particles_start": state.start.get("particles"),
              "held_mass_start_kg": state.start.get("held_mass_kg"),
              "inflow_mass_kg": _since_start(dem.emitted_mass, state.start, "emitted_mass_kg"),
              "particles_end": dem.n, "held_mass_end_kg": dem.held_mass(),
              "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    runs = work / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    if reason:
        from surrogate.dem import plots

        # the pile at the failure, coloured by speed (where the contacts gave way)
        pictures = plots.pile_pictures(dem.snapshot(), runs / f"{key}_failure",
                                       run=f"{run.name} at the failure, t = {dem.time:.2f} s")
        record.update(status="unstable", unstable_in_control_step=state.step,
                      unstable_dem_time_s=dem.time, unstable_reason=reason,
                      failure_picture=str(next(p for p in pictures
                                               if p.name == "pile_speed.png")
                                          .relative_to(work)))
        _write_json(runs / f"{key}.json", record)
        _say(progress, f"run {run.name} ({key}): UNSTABLE at control step {state.step}: "
                       f"{reason}; recorded, the design goes on")
        return record
    result = compact_result(state)
    tmp = runs / f"{key}.npz.tmp"
    with open(tmp, "wb") as handle:
        np.savez_compressed(handle, **result)
    os.replace(tmp, runs / f"{key}.npz")
    states = work / "states"
    states.mkdir(parents=True, exist_ok=True)
    tmp = states / f"run_{key}.npz.tmp"
    dem.save_checkpoint(tmp)
    os.replace(tmp, states / f"run_{key}.npz")
    outflow = _since_start(dem.discharged_mass, state.start, "discharged_mass_kg")
    record.update(status="done", samples=int(result["time"].size),
                  discharged_mass_kg=outflow,
                  mass_balance_error=dem.mass_balance_error(),
                  result_bytes=(runs / f"{key}.npz").stat().st_size)
    _write_json(runs / f"{key}.json", record)
    shutil.rmtree(partial, ignore_errors=True)
    _say(progress, f"run {run.name} ({key}): done, {record['samples']} samples, "
                   f"{record['result_bytes'] / 1e6:.2f} MB, wall {_duration(state.wall)}, "
                   f"{state.particle_steps:.3g} particle-steps")
    return record


def perturb(dem, run: RunSpec) -> None:
    """Move every disk by ``run.perturbation`` [m] in a direction of its own,
    drawn from the run's seed and replica (the DEM is chaotic: replicas that
    start this close end as independent realisations)."""
    rng = np.random.default_rng([run.seed, 11, run.replica])
    angle = rng.uniform(0.0, 2.0 * np.pi, dem.n)
    dem.pos = dem.pos + run.perturbation * np.column_stack((np.cos(angle), np.sin(angle)))


def _since_start(total: float, start: dict, key: str):
    """``total`` minus its value at the run's start [kg] (None for a run
    resumed from a checkpoint that did not record it)."""
    return None if key not in start else float(total - start[key])


def compact_result(state: _RunState) -> dict:
    """The run's compact arrays (module docstring): float32 fields, uint64 ids."""
    result = {k: np.asarray(v, dtype=np.float32) for k, v in state.samples.items()}
    count = len(state.samples["time"])
    if count == 0:  # keep the shapes of an empty run well defined
        result = {k: np.zeros((0,), np.float32) for k in SAMPLE_KEYS}
    outflow = _join_outflow(state.outflow)
    for k in _OUTFLOW_KEYS:
        kind = np.uint64 if k in ("id", "tracking_id") else np.float32
        result[f"out_{k}"] = np.asarray(outflow[k], dtype=kind)
    if state.inflow:  # float64: the particles other models are fed must be the DEM's own
        result.update({f"in_{k}": v for k, v in _join_outflow(state.inflow).items()})
    return result


def _write_json(path: Path, payload) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(payload, indent=1, allow_nan=False, default=_jsonable))
    os.replace(tmp, path)


def _jsonable(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _say(progress, message: str) -> None:
    if progress:
        progress(message)


def _duration(seconds: float) -> str:
    seconds = max(float(seconds), 0.0)
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


# ------------------------------------------------------------ the design
def mean_disk_mass(cfg) -> float:
    from surrogate.dem.emitter import mean_particle_mass

    return mean_particle_mass(cfg)


def estimate(design: Design) -> dict:
    """Planned cost of every pile and run: DEM particle-steps (steps x mean
    disks held; a run's disks change by (inflow - discharge) x duration /
    mean disk mass), keyed by name. A nonsmooth step (``nonsmooth_dt``) runs
    ``solver_iterations`` sweeps over the contacts, so its particle-steps cost far
    more each than the explicit method's: give ``--rate`` for that method."""
    cfg = design.config
    dt = cfg.nonsmooth_dt if cfg.method == "nonsmooth" else cfg.stable_dt
    mean_mass = mean_disk_mass(design.config)
    cost, end_particles = {}, {}
    for pile in design.piles:
        cost[pile.name] = pile.settle_time / dt * pile.particles
        end_particles[f"pile:{pile.name}"] = pile.particles
    for run in design.runs:
        start = end_particles[run.start]
        change = (run.inflow_rate - run.discharge_rate) * run.duration / mean_mass
        cost[run.name] = run.duration / dt * (start + 0.5 * change)
        end_particles[f"run:{run.name}"] = start + change
    return cost


def _load_records(directory: Path) -> dict:
    """Records by key of the finished runs in a work directory's ``runs/``."""
    records = {}
    for path in sorted((directory / "runs").glob("*.json")) if directory.is_dir() else []:
        record = json.loads(path.read_text())
        records[record["key"]] = record
    return records


def committed_keys(data: Path | None) -> dict:
    """Keys -> records of the runs in a data folder's manifest (none without one)."""
    if data is None or not (Path(data) / "manifest.json").is_file():
        return {}
    manifest = json.loads((Path(data) / "manifest.json").read_text())
    return {r["key"]: r for r in manifest.get("runs", [])
            if r.get("status") == "done" and (Path(data) / "train" / f"{r['name']}.npz").is_file()}


def _state_path(work: Path, data: Path | None, key: str) -> Path | None:
    for folder in (work / "states", None if data is None else Path(data) / "states"):
        if folder is not None and (folder / f"{key}.npz").is_file():
            return folder / f"{key}.npz"
    return None


def _pile_job(design: Design, pile: PileSpec, work: Path) -> dict:
    key = "pile_" + pile_key(design, pile)
    dem, record = build_pile(design, pile, progress=_stderr)
    states = work / "states"
    states.mkdir(parents=True, exist_ok=True)
    tmp = states / f"{key}.npz.tmp"
    dem.save_checkpoint(tmp)
    os.replace(tmp, states / f"{key}.npz")
    record.update(key=key, git_commit=batch.code_version(), design_version=DESIGN_VERSION)
    _write_json(states / f"{key}.json", record)
    _stderr(f"pile {pile.name} ({key}): {record['particles']} disks, "
            f"{record['held_mass_kg'] / 1e3:.0f} t, wall {_duration(record['wall_s'])}")
    return record


def _run_job(design: Design, run: RunSpec, work: Path, start_path: Path, data) -> dict:
    return run_one(design, run, work, start_path, progress=_stderr, data=data)


def _stderr(message: str) -> None:
    print(f"{time.strftime('%H:%M:%S')} {message}", file=sys.stderr, flush=True)


def run_design(design: Design, work, data=None, workers: int = 2, progress=_stderr,
               executor=None) -> dict:
    """Run every pile and run of ``design`` not yet done on ``executor``
    (``cosim.batch``; default: ``workers`` local processes), most valuable
    first (``Design.runs`` order) as soon as their start states exist; write
    ``work/manifest.json``. Runs whose result is in ``work`` or in the data
    folder ``data`` are skipped, interrupted runs resume from their latest
    checkpoint (also a run whose worker died, run again at most
    ``executor.retries`` times), a run that blows up or raises is recorded
    and the others go on. Returns the manifest."""
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    # the code and commit the workers (forked) run with: nothing edited later is loaded
    import surrogate.dem.builders  # noqa: F401
    batch.code_version()
    _write_json(work / "design.json", design_description(design))
    cost = estimate(design)
    finished = {**committed_keys(data), **_load_records(work)}
    done = {k for k, r in finished.items() if r.get("status") == "done"}
    failed = {k for k, r in finished.items() if r.get("status") == "unstable"}
    run_keys = {r.name: run_key(design, r) for r in design.runs}
    pile_keys = {p.name: "pile_" + pile_key(design, p) for p in design.piles}

    def state_of(start: str) -> str:
        return start_key(design, start)

    # a run is needed if its result is missing, or its end state is missing
    # and a run that is needed starts from it
    def blocked(run) -> bool:  # the run or a run it starts from blew up
        if run_keys[run.name] in failed:
            return True
        return run.start.startswith("run:") and blocked(design.run(run.start[4:]))

    needed, grown = set(), True
    while grown:  # until no run is added: parents of needed runs whose end state is gone
        grown = False
        for run in design.runs:
            key = run_keys[run.name]
            if run.name in needed or blocked(run):
                continue
            children = [r for r in design.runs
                        if r.start == f"run:{run.name}" and r.name in needed]
            if key not in done or (children and _state_path(work, data, "run_" + key) is None):
                needed.add(run.name)
                grown = True
    piles_needed = {p.name for p in design.piles
                    if _state_path(work, data, pile_keys[p.name]) is None
                    and any(r.start == f"pile:{p.name}" and r.name in needed
                            for r in design.runs)}
    order = [("pile", p.name) for p in design.piles if p.name in piles_needed]
    order += [("run", r.name) for r in design.runs if r.name in needed]
    total = sum(cost[name] for _, name in order)
    _say(progress, f"design {design.name}: {len(design.runs)} runs, {len(done & set(run_keys.values()))} "
                   f"done, {len(order)} jobs to do ({total:.3g} particle-steps planned); "
                   f"work {work}")
    started = time.perf_counter()
    spent = 0.0

    def ready(job) -> Path | bool | None:
        kind, name = job
        if kind == "pile":
            return True
        run = design.run(name)
        if run.start.startswith("run:") and run_keys[run.start[4:]] in failed:
            return None  # blocked for good
        return _state_path(work, data, state_of(run.start))

    pending, running, attempts = list(order), {}, {}
    own = executor is None
    executor = batch.LocalExecutor(workers) if own else executor
    try:
        while pending or running:
            for job in list(pending):
                if len(running) >= executor.workers:
                    break
                start_path = ready(job)
                if start_path is None and job[0] == "run" and \
                        design.run(job[1]).start.startswith("run:") and \
                        run_keys[design.run(job[1]).start[4:]] in failed:
                    pending.remove(job)
                    _say(progress, f"run {job[1]}: skipped, its start run blew up")
                    continue
                if not start_path:
                    continue
                pending.remove(job)
                if job[0] == "pile":
                    call = (_pile_job, {"design": design, "pile": design.pile(job[1]),
                                        "work": work})
                else:
                    call = (_run_job, {"design": design, "run": design.run(job[1]),
                                       "work": work, "start_path": start_path, "data": data})
                attempts[job] = attempts.get(job, 0) + 1
                running[executor.submit(*call)] = job
            if not running:
                if pending:  # nothing can start: the missing start states will not come
                    _say(progress, f"blocked: {[name for _, name in pending]}")
                break
            while not (finished := executor.wait(list(running), timeout=STATUS_EVERY_S)):
                now = spent + sum(_progress_of(design, work, job) * cost[job[1]]
                                  for job in running.values())
                _say(progress, _status(design, now, total, time.perf_counter() - started,
                                       len(order) - len(pending) - len(running), len(order)))
            for handle in finished:
                job = running.pop(handle)
                record = _outcome(job, executor, handle, progress)
                if record is None:  # its worker died: run again, resuming its checkpoint
                    if attempts[job] <= executor.retries:
                        pending.insert(0, job)
                        _say(progress, f"{job[0]} {job[1]}: its worker died; run again "
                                       f"(attempt {attempts[job] + 1})")
                        continue
                    record = {"status": "error", "error": "its worker died "
                                                          f"{attempts[job]} times"}
                spent += cost[job[1]]
                if job[0] == "run" and record.get("status") != "done":
                    failed.add(run_keys[job[1]])  # an error: retried by the next start
                _say(progress, f"{job[0]} {job[1]} finished; " + _status(
                    design, spent, total, time.perf_counter() - started,
                    len(order) - len(pending) - len(running), len(order)))
            write_manifest(design, work)
    finally:
        if own:
            executor.close()
    return write_manifest(design, work)


def _outcome(job, executor, handle, progress) -> dict | None:
    """A finished job's record; an exception (a bug) becomes a record with
    status ``error`` so the other runs go on; None when its worker died and
    the executor does not run it again by itself."""
    try:
        return executor.outcome(handle)["value"]
    except batch.WorkerLost as exc:
        if not executor.retries_on_its_own:
            return None
        error = f"WorkerLost: {exc}"
    except batch.TaskFailed as exc:
        error = str(exc)
    _say(progress, f"{job[0]} {job[1]}: ERROR {error}; the design goes on (the run is "
                   "retried when the design is restarted)")
    return {"status": "error", "error": error}


def status(design: Design, work, data=None) -> list[dict]:
    """Per run: ``done`` (in ``work`` or ``data``), ``unstable``, ``partial``
    (simulated seconds reached by its latest checkpoint) or ``pending``, with
    its planned particle-steps."""
    work = Path(work)
    finished = {**committed_keys(data), **_load_records(work)}
    cost = estimate(design)
    rows = []
    for run in design.runs:
        key = run_key(design, run)
        record = finished.get(key)
        row = {"name": run.name, "key": key, "planned_particle_steps": cost[run.name]}
        if record is not None:
            row.update(state=record["status"], wall_s=record.get("wall_s"),
                       result_bytes=record.get("result_bytes"))
        elif any(latest_checkpoint(folder / "partial" / key) is not None for folder in
                 [work] + ([] if data is None else [Path(data)])):
            folder = work if latest_checkpoint(work / "partial" / key) else Path(data)
            row.update(state="partial", simulated_s=_progress_of(design, folder,
                                                                 ("run", run.name))
                       * run.duration, duration_s=run.duration)
        else:
            row.update(state="pending")
        rows.append(row)
    return rows


STATUS_EVERY_S = 600.0
"""Wall seconds between the design's status lines while runs are under way."""


def _progress_of(design: Design, work: Path, job) -> float:
    """Fraction [0, 1] of a running job done, from its latest checkpoint."""
    if job[0] != "run":
        return 0.0
    run = design.run(job[1])
    latest = latest_checkpoint(work / "partial" / run_key(design, run))
    if latest is None:
        return 0.0
    with np.load(latest[1], allow_pickle=False) as data:
        step = json.loads(str(data["meta"]))["step"]
    return min(step * doe.CONTROL_STEP / run.duration, 1.0)


def _status(design: Design, spent: float, total: float, elapsed: float, done: int,
            jobs: int) -> str:
    """One progress line (tqdm's): particle-steps done of those planned, the pace and
    the ETA at this session's pace, and the jobs done."""
    return tqdm.format_meter(min(spent, total), total, elapsed, prefix=f"design {design.name}",
                             unit="particle-steps", unit_scale=True, ascii=True,
                             postfix=f"{done}/{jobs} jobs done")


def design_description(design: Design) -> dict:
    """The design as strict JSON: config, grid, piles and runs with their keys."""
    return {"design": design.name, "design_version": DESIGN_VERSION,
            "dem_config": design.config.to_dict(), "grid": design.grid.to_dict(),
            "dt_s": design.config.stable_dt, "dt_over_tc": STEP_FRACTION,
            "checkpoint_interval_s": design.checkpoint_interval,
            "piles": [{**asdict(p), "key": "pile_" + pile_key(design, p)} for p in design.piles],
            "runs": [{**asdict(r), "key": run_key(design, r),
                      "start_key": start_key(design, r.start)} for r in design.runs],
            "planned_particle_steps": estimate(design)}


def write_manifest(design: Design, work: Path) -> dict:
    """``work/manifest.json``: the design and the records of its finished runs and piles."""
    work = Path(work)
    keys = {run_key(design, r) for r in design.runs}
    piles = []
    for pile in design.piles:
        path = work / "states" / f"pile_{pile_key(design, pile)}.json"
        if path.is_file():
            piles.append(json.loads(path.read_text()))
    manifest = {**design_description(design),
                "piles_built": piles,
                "runs_finished": [r for k, r in _load_records(work).items() if k in keys]}
    _write_json(work / "manifest.json", manifest)
    return manifest


def export(design: Design, work, data, with_partial: bool = False) -> dict:
    """Copy the compact results of ``work``'s finished runs into the data folder
    ``data`` (``train/<name>.npz``), with ``manifest.json`` (the design, every
    finished run's record, the base piles') and ``doe.json`` (config, grid and
    the ROM's container, from the first base pile's measured density and angle
    of repose: what ``minetwin rom train`` reads). Runs already in ``data``
    and not in ``work`` are kept. The start states of the runs not yet done
    go to ``states/`` (DEM checkpoints, so a session without ``work`` starts
    them without redoing their parents) and, with ``with_partial``, the latest
    checkpoint of each interrupted run to ``partial/<key>/``. Returns the data
    manifest."""
    work, data = Path(work), Path(data)
    (data / "train").mkdir(parents=True, exist_ok=True)
    keys = {run_key(design, r): r.name for r in design.runs}
    records = {k: r for k, r in committed_keys(data).items() if k in keys}
    for key, record in _load_records(work).items():
        if key not in keys or record.get("status") != "done":
            continue
        name = keys[key]
        shutil.copyfile(work / "runs" / f"{key}.npz", data / "train" / f"{name}.npz.tmp")
        os.replace(data / "train" / f"{name}.npz.tmp", data / "train" / f"{name}.npz")
        records[key] = record
    for path in (data / "train").glob("*.npz"):  # results of runs no longer in the design
        if path.stem not in {r["name"] for r in records.values()}:
            path.unlink()
    unstable = _export_failures(work, data, keys, records)
    piles = write_manifest(design, work)["piles_built"] if work.is_dir() else []
    old = json.loads((data / "manifest.json").read_text()) if (data / "manifest.json").is_file() \
        else {}
    if not piles:
        piles = old.get("piles", [])
    ordered = [records[run_key(design, r)] for r in design.runs if run_key(design, r) in records]
    manifest = {**design_description(design), "piles": piles, "runs": ordered,
                "runs_done": len(ordered), "runs_total": len(design.runs),
                "runs_unstable": [unstable[run_key(design, r)] for r in design.runs
                                  if run_key(design, r) in unstable],
                "bytes": sum(r["result_bytes"] for r in ordered),
                "dem_cpu_hours": sum(r["cpu_s"] for r in ordered) / 3600.0,
                "regenerate": f"minetwin rom design --design {design.name} --work DIR "
                              f"--data {data} --workers 2"
                              + "".join(f" --set {k}={json.dumps(v)}"
                                        for k, v in design.changed)}
    manifest["state_bytes"] = _export_states(design, work, data, set(records) | set(unstable),
                                             with_partial)
    _write_json(data / "manifest.json", manifest)
    if piles:
        base = piles[0]
        container = doe.container_of(design.config, base["areal_density_kg_m2"],
                                     base["repose_angle_rad"])
        doe.write_meta(data, design.config, design.grid, container,
                       {"design": design.name, "scenarios": [r["spec"] for r in ordered]})
    return manifest


def _export_failures(work: Path, data: Path, keys: dict, done: dict) -> dict:
    """Records of the runs that blew up (the guard stopped them; they have no
    result), by key, with their picture at the failure copied to
    ``failures/<name>_speed.png`` (the path in the record then relative to
    ``data``); those of an earlier export are kept unless the run finished since."""
    old = json.loads((data / "manifest.json").read_text()) if (data / "manifest.json").is_file() \
        else {}
    unstable = {r["key"]: r for r in old.get("runs_unstable", []) if r["key"] not in done}
    for key, record in _load_records(work).items() if work.is_dir() else []:
        if key not in keys or record.get("status") != "unstable":
            continue
        record = dict(record)
        picture = work / record.get("failure_picture", "")
        if record.get("failure_picture") and picture.is_file():
            target = data / "failures" / f"{keys[key]}_speed.png"
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(picture, target)
            record["failure_picture"] = str(target.relative_to(data))
        unstable[key] = record
    return unstable


def _export_states(design: Design, work: Path, data: Path, done: set,
                   with_partial: bool) -> int:
    """Copy the start states (and optionally the latest checkpoints) of the
    runs not in ``done`` into ``data``; drop those no run needs any more;
    return their bytes."""
    pending = [r for r in design.runs if run_key(design, r) not in done]
    wanted = {start_key(design, r.start)
              for r in (design.runs if design.keep_start_states else pending)}
    states = data / "states"
    states.mkdir(parents=True, exist_ok=True)
    for key in wanted:
        source = work / "states" / f"{key}.npz"
        if source.is_file():
            shutil.copyfile(source, states / f"{key}.npz.tmp")
            os.replace(states / f"{key}.npz.tmp", states / f"{key}.npz")
    for path in states.glob("*.npz"):
        if path.name[:-4] not in wanted:
            path.unlink()
    partial = data / "partial"
    keep = set()
    for run in pending if with_partial else []:
        key = run_key(design, run)
        latest = latest_checkpoint(work / "partial" / key)
        if latest is None:
            if latest_checkpoint(partial / key):
                keep.add(key)
            continue
        target = partial / key
        shutil.rmtree(target, ignore_errors=True)
        target.mkdir(parents=True)
        for path in latest:
            shutil.copyfile(path, target / path.name)
        keep.add(key)
    for folder in partial.glob("*") if partial.is_dir() else []:
        if folder.name not in keep and (with_partial or folder.name not in
                                        {run_key(design, r) for r in pending}):
            shutil.rmtree(folder, ignore_errors=True)
    return sum(p.stat().st_size for p in list(states.glob("*.npz")) + list(partial.rglob("*.npz")))
