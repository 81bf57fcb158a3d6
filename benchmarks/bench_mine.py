"""Real-time factor of the mine simulator at the paper's scale; prints JSON.

The paper's plant (examples/paper_scale.toml: two sources, one haul truck
on the 55 s cycle, jaw crusher FMU, two belts, a 2,000 t stockpile holding
about 19,000 pseudo-particles, mill FMU) is run for 7,200 s with each
storage model (FIFO, perfect mixing and the shipped paper-scale ROM with its
DEM surface layer), recording every event to SQLite as ``minetwin simulate``
does. Reported per model: simulated seconds per wall second (targets on one
core: >= 200x with FIFO or mixing, >= 100x with the ROM) by wall clock and by
the process's CPU time (the fairer figure on a shared machine; the load
average is printed), particles created, events. Each model first runs 5 s
untimed, so compiling its kernels is not counted.
A separate shorter FIFO run under cProfile gives the top entries of where
the time goes.

    python benchmarks/bench_mine.py [--until 7200] [--profile-until 1800]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import pstats
import sqlite3
import sys
import tempfile
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim import jsonio  # noqa: E402
from cosim.scenario import build, load, run_scenario  # noqa: E402
from minetwin.acceptance import timed_scenario  # noqa: E402

SCENARIO = ROOT / "examples" / "paper_scale.toml"


def timed_run(config: dict, model: str, until: float) -> dict:
    with tempfile.TemporaryDirectory() as out:
        simulation, summary, timing = timed_scenario(config, out, until, storage_model=model)
        with sqlite3.connect(Path(out) / "events.sqlite") as db:
            events = db.execute("SELECT COUNT(*) FROM events").fetchone()[0]
            rows = db.execute("SELECT COUNT(*) FROM event_particles").fetchone()[0]
    wall, cpu = timing["wall_s"], timing["cpu_s"]
    stockpile = simulation.timeseries["stockpile.mass_kg"]
    return {
        "storage_model": model, "simulated_s": until, "wall_s": round(wall, 2),
        "realtime_factor": round(until / wall, 1),
        "cpu_s": round(cpu, 2), "realtime_factor_cpu": round(until / cpu, 1),
        "particles_created": summary["particles_created"],
        "stockpile_mass_mean_t": round(float(stockpile.mean()) / 1e3, 1),
        "stockpile_particles_end": timing["stockpile_particles_end"],
        "events": events, "event_particle_rows": rows,
        "mass_balance_rel_error": summary["mass_balance_rel_error"],
        "warnings": timing["warnings"],
    }


def profile(config: dict, until: float, top: int = 15) -> list[dict]:
    simulation = build(config, storage_model="fifo")
    profiler = cProfile.Profile()
    profiler.enable()
    simulation.run(until)
    simulation.close()
    profiler.disable()
    stats = pstats.Stats(profiler, stream=io.StringIO())
    total = stats.total_tt
    rows = []
    for (filename, line, name), (_, calls, tottime, cumtime, _) in sorted(
            stats.stats.items(), key=lambda item: -item[1][2])[:top]:
        where = Path(filename)
        label = f"{where.parent.name}/{where.name}:{line}({name})" if line else name
        rows.append({"function": label, "calls": calls, "tottime_s": round(tottime, 3),
                     "share": round(tottime / total, 3), "cumtime_s": round(cumtime, 3)})
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--until", type=float, default=7200.0, help="simulated time [s]")
    parser.add_argument("--profile-until", type=float, default=1800.0,
                        help="simulated time of the profiled FIFO run [s] (0: skip)")
    parser.add_argument("--models", default="fifo,mixing,rom", help="storage models to time")
    args = parser.parse_args()
    config = load(SCENARIO)
    models = args.models.split(",")
    for model in models:  # compile/load each model's numba kernels outside the timing
        with tempfile.TemporaryDirectory() as out, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            run_scenario(config, out, until=5.0, storage_model=model)
    result = {"scenario": str(SCENARIO.relative_to(ROOT)),
              "target_realtime_factor": {"fifo": 200, "mixing": 200, "rom": 100},
              "load_average_at_start": os.getloadavg()[0],
              "runs": [timed_run(config, model, args.until) for model in models]}
    if args.profile_until > 0:
        result["profile_fifo"] = {"simulated_s": args.profile_until,
                                  "top_by_own_time": profile(config, args.profile_until)}
    print(jsonio.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
