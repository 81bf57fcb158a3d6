"""The nonsmooth DEM under a falling inflow, with and without its missed-contact
check (issue 22), over seeds.

Scene: a pile of ``--particles`` disks (``packed_pile``, the layout seed one of
``--seeds``) settled by the nonsmooth method, with inlets ``--fall`` m above
it (1 m wide) and a 6 m outlet in the floor. For ``--seconds`` of simulated
time the inlet emits ``--rate`` kg/s as one lot per second (as the paper
design's control step emits: a short column of touching disks that lands at
about 22 m/s from 27 m) and the feeder draws the same rate. Each seed runs
with ``missed_contact_resolves`` 3 (the default) and 0 (the check off),
alternated, at the paper's 11 ms and 100 sweeps (the method runs in one
thread).

Prints one JSON object: per run the seed, the setting, whether the blow-up
guard stopped it (and when, and why), the largest overlap over the smaller
diameter seen at the end of each second, CPU seconds per simulated second
(until it ended) and re-solves per step; and per setting the runs the guard
stopped and the median CPU cost, with the ratio of the two settings' costs
per seed. The trajectories are chaotic: compare counts and medians over
seeds, not one run.

Run: ``.venv/bin/python benchmarks/bench_nonsmooth_inflow.py [--seeds 1,2,3]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from cosim import jsonio
from surrogate.dem import Dem, DemConfig
from surrogate.dem.builders import config_for_particles, packed_pile, settle
from surrogate.dem.simulation import DemBlowUp

SETTINGS = (3, 0)
"""``missed_contact_resolves`` of the two settings compared."""


def settled_pile(particles: int, fall: float, seed: int, cache: Path) -> Path:
    """The settled start state of one seed (built once, kept in ``cache``)."""
    path = cache / f"nonsmooth_inflow_{particles}_{fall:g}_{seed}.npz"
    if not path.is_file():
        base = DemConfig(method="nonsmooth", inlet_width=1.0, outlet_width=6.0)
        dem = packed_pile(config_for_particles(particles, base, inlet_clearance=fall),
                          particles, seed=seed)
        settle(dem, max_time=6.0)
        cache.mkdir(parents=True, exist_ok=True)
        dem.save_checkpoint(path)
    return path


def run(start: Path, resolves: int, rate: float, seconds: float, seed: int) -> dict:
    dem = Dem.load_checkpoint(start, {"missed_contact_resolves": resolves})
    settling = dem.solver_stats.copy()  # the checkpoint's counters are the settling's
    dem.set_discharge_rate(rate)
    f16 = np.zeros(16)
    f16[12] = 1.0
    t0 = dem.time
    worst, failure, lot = 0.0, None, 0
    tic = time.process_time()
    try:
        while dem.time - t0 < seconds - 1e-9:
            dem.emit(rate, 0.5, 1.0, f16, lot, inlet=0)
            lot += 1
            dem.advance(1.0)
            worst = max(worst, dem.max_overlap_ratio())
    except DemBlowUp as blow_up:
        failure = {"kind": blow_up.kind, "after_s": dem.time - t0, "message": str(blow_up)}
    cpu = time.process_time() - tic
    stats = dem.solver_stats - settling
    return {"seed": seed, "missed_contact_resolves": resolves, "blew_up": failure,
            "simulated_s": dem.time - t0, "largest_overlap_over_diameter": worst,
            "cpu_s_per_simulated_s": cpu / max(dem.time - t0, 1e-9),
            "resolves_per_step": float(stats[4] / stats[0]) if stats[0] else 0.0,
            "sweeps_per_step": float(stats[1] / stats[0]) if stats[0] else 0.0}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", type=int, default=2000)
    parser.add_argument("--fall", type=float, default=27.0,
                        help="inlet height above the pile's top [m] (27)")
    parser.add_argument("--rate", type=float, default=1200.0, help="inflow and feeder [kg/s]")
    parser.add_argument("--seconds", type=float, default=40.0)
    parser.add_argument("--seeds", default="1,2,3")
    parser.add_argument("--cache", type=Path, default=Path("/tmp/minetwin_nonsmooth_inflow"))
    args = parser.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    rows = []
    for seed in seeds:
        start = settled_pile(args.particles, args.fall, seed, args.cache)
        for resolves in SETTINGS:
            row = run(start, resolves, args.rate, args.seconds, seed)
            print(jsonio.dumps(row), file=sys.stderr, flush=True)
            rows.append(row)
    summary = {}
    for resolves in SETTINGS:
        own = [r for r in rows if r["missed_contact_resolves"] == resolves]
        summary[str(resolves)] = {
            "runs": len(own), "blew_up": sum(r["blew_up"] is not None for r in own),
            "median_cpu_s_per_simulated_s": float(np.median(
                [r["cpu_s_per_simulated_s"] for r in own]))}
    ratio = [a["cpu_s_per_simulated_s"] / b["cpu_s_per_simulated_s"]
             for a, b in zip(rows[0::2], rows[1::2])]
    print(jsonio.dumps({"particles": args.particles, "fall_m": args.fall, "rate_kg_s": args.rate,
                        "seconds": args.seconds, "rows": rows, "by_setting": summary,
                        "cost_ratio_check_on_over_off": ratio}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
