"""Cost of the two DEM methods on the same settled pile, as ratios in one run (issue 22).

Scene: a dense 2D pile of ``--particles`` disks (``packed_pile``, settled for
``--settle`` s with the explicit DEM; cached in ``--cache``). From that state
each method runs ``--seconds`` of simulated time with the feeder at
``--rate`` kg/s, alternated ``--pairs`` times:

* explicit at its configured step (``DemConfig``'s default t_c / 15; a
  ``--cache`` pile of another config keeps its own, e.g. the paper-scale
  designs' 0.16 t_c) and at ``--explicit-factor`` times it (3.3: 0.22 t_c from
  t_c / 15, the largest step measured stable on a dense pile); a run the
  blow-up guard stops is reported with ``blew_up`` (its reason) and its cost
  until then;
* nonsmooth at the paper's 11 ms and 100 sweeps, with the paper's plain
  Gauss-Seidel and over-relaxed (``--relaxation``, 1.9: projected SOR of the
  normal impulses, Cryer 1971; ``DemConfig.solver_relaxation``).

Prints one JSON object with wall seconds per simulated second of each, the
ratios explicit / nonsmooth, the discharged mass, the mean and largest
overlap (penetration) over the smaller diameter at the end, and the
nonsmooth solver's mean sweeps per step. Small by default (2,000 disks, a
few minutes); ``--particles 20000`` is the paper's scale (long).

Run: ``.venv/bin/python benchmarks/bench_dem_methods.py``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from cosim import jsonio
from surrogate.dem import Dem, DemConfig
from surrogate.dem.simulation import DemBlowUp
from surrogate.dem.builders import config_for_particles, packed_pile, settle


def run(path: Path, method: str, factor: float, seconds: float, rate: float,
        stiffness: float | None, relaxation: float = 1.0) -> dict:
    changes = {"method": method}
    if relaxation != 1.0:
        changes["solver_relaxation"] = relaxation
    if stiffness:
        changes["normal_stiffness"] = stiffness
    dem = Dem.load_checkpoint(path, changes)
    if method == "explicit":
        dem.set_dt(factor * dem.stable_dt, force=factor > 1)
    dem.set_discharge_rate(rate)
    dem.step(2)  # loads the compiled kernels outside the timing
    dem.discharged()
    start = dem.time
    tic = time.perf_counter()
    blew_up = None
    try:
        dem.advance(seconds)
    except DemBlowUp as failure:  # a forced step: the guard's reason is the result
        blew_up = str(failure)
    wall = time.perf_counter() - tic
    mean, worst = dem.overlap_stats()
    stats = dem.solver_stats
    return {"method": method, "dt_s": dem.dt, "solver_relaxation": relaxation,
            "blew_up": blew_up,
            "wall_s_per_simulated_s": wall / max(dem.time - start, 1e-12),
            "discharged_kg": float(dem.discharged()["mass"].sum()),
            "mean_overlap_over_diameter": mean, "max_overlap_over_diameter": worst,
            "mean_sweeps_per_step": float(stats[1] / stats[0]) if stats[0] else None}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", type=int, default=2000)
    parser.add_argument("--settle", type=float, default=2.0)
    parser.add_argument("--seconds", type=float, default=1.0)
    parser.add_argument("--rate", type=float, default=500.0)
    parser.add_argument("--explicit-factor", type=float, default=3.3)
    parser.add_argument("--pairs", type=int, default=1)
    parser.add_argument("--relaxation", type=float, default=1.9,
                        help="solver_relaxation of the over-relaxed nonsmooth row (1.9)")
    parser.add_argument("--normal-stiffness", type=float,
                        help="k_n [N/m] of the timed runs (default: the pile's, 4e7); the pile "
                             "is settled at the default and continues at this one")
    parser.add_argument("--cache", type=Path, default=Path("/tmp/minetwin_methods_pile.npz"))
    args = parser.parse_args(argv)
    if not 0.0 < args.relaxation < 2.0:
        print(f"bench_dem_methods: --relaxation: must be in (0, 2) (got {args.relaxation:g})",
              file=sys.stderr)
        return 2
    cfg = config_for_particles(args.particles, DemConfig())
    if not args.cache.is_file() or Dem.load_checkpoint(args.cache).n != args.particles:
        dem = packed_pile(cfg, args.particles, seed=0)
        settle(dem, max_time=args.settle)
        dem.save_checkpoint(args.cache)
    rows = []
    for _ in range(args.pairs):
        for method, factor, relaxation in (
                ("explicit", 1.0, 1.0), ("explicit", args.explicit_factor, 1.0),
                ("nonsmooth", 1.0, 1.0), ("nonsmooth", 1.0, args.relaxation)):
            row = run(args.cache, method, factor, args.seconds, args.rate,
                      args.normal_stiffness, relaxation)
            print(jsonio.dumps(row), file=sys.stderr, flush=True)
            rows.append(row)
    cost = {}
    for row in rows:
        key = f"{row['method']}_{row['dt_s']:.3g}s" + (
            f"_relaxed{row['solver_relaxation']:g}" if row["solver_relaxation"] != 1.0 else "")
        cost.setdefault(key, []).append(row["wall_s_per_simulated_s"])
    median = {k: float(np.median(v)) for k, v in cost.items()}
    ns = next(v for k, v in median.items() if k.startswith("nonsmooth") and "relaxed" not in k)
    print(jsonio.dumps({"particles": args.particles, "normal_stiffness": args.normal_stiffness
                        or cfg.normal_stiffness, "rows": rows,
                        "median_wall_s_per_simulated_s": median,
                        "ratio_to_nonsmooth": {k: v / ns for k, v in median.items()}},
                       indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
