"""Speed-up of the explicit DEM from a second thread, as a ratio in one run (issue 22).

Scene: a dense 2D pile of ``--particles`` disks (20,000: the paper's scale)
laid out with ``packed_pile`` and settled for ``--settle`` simulated seconds
(cached in ``--cache``). From that state the same ``--steps`` steps run
alternately at 1 and 2 threads (``Dem.threads``),
``--pairs`` times; each run starts from the same checkpoint, and the
benchmark checks that both thread counts end on the same bits. Prints one
JSON object: wall seconds of each run, particle-steps per wall second, and
the median of the per-pair ratios t(1 thread) / t(2 threads) with its range.
On a machine shared with other jobs the ratio is a lower bound: the second
thread competes with them.

Run: ``.venv/bin/python benchmarks/bench_dem_threads.py`` (a few minutes the
first time, for settling; ``--particles 5000`` for a quick look).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numba
import numpy as np

from cosim import jsonio
from surrogate.dem import Dem, DemConfig
from surrogate.dem.builders import config_for_particles, packed_pile, settle


def settled(n: int, settle_time: float, cache: Path) -> Path:
    if cache.is_file():
        dem = Dem.load_checkpoint(cache)
        if dem.n == n and dem.cfg == config_for_particles(n, DemConfig()):
            return cache
    dem = packed_pile(config_for_particles(n, DemConfig()), n, seed=0)
    settle(dem, max_time=settle_time, speed=0.05, chunk=0.25)
    dem.save_checkpoint(cache)
    return cache


def timed(path: Path, threads: int, steps: int):
    dem = Dem.load_checkpoint(path)
    dem.threads = threads
    dem.step(2)  # loads the compiled kernels outside the timing
    tic = time.perf_counter()
    dem.step(steps)
    return time.perf_counter() - tic, dem


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", type=int, default=20_000)
    parser.add_argument("--settle", type=float, default=2.0, help="settling time [s] (2)")
    parser.add_argument("--steps", type=int, default=400, help="steps per timed run (400)")
    parser.add_argument("--pairs", type=int, default=3, help="alternated 1/2-thread pairs (3)")
    parser.add_argument("--cache", type=Path, default=Path("/tmp/minetwin_thread_pile.npz"))
    args = parser.parse_args(argv)
    if numba.config.NUMBA_NUM_THREADS < 2:
        print("bench_dem_threads: needs NUMBA_NUM_THREADS >= 2", file=sys.stderr)
        return 2
    path = settled(args.particles, args.settle, args.cache)
    rows, ratios, same = [], [], True
    for _ in range(args.pairs):
        one, dem_one = timed(path, 1, args.steps)
        two, dem_two = timed(path, 2, args.steps)
        same &= bool(np.array_equal(dem_one.pos, dem_two.pos)
                     and np.array_equal(dem_one.vel, dem_two.vel))
        rows.append({"one_thread_s": one, "two_threads_s": two})
        ratios.append(one / two)
    n = dem_one.n
    print(jsonio.dumps({
        "particles": n, "steps": args.steps, "runs": rows,
        "particle_steps_per_s_one_thread": n * args.steps / min(r["one_thread_s"] for r in rows),
        "particle_steps_per_s_two_threads": n * args.steps / min(r["two_threads_s"] for r in rows),
        "speedup_median": float(np.median(ratios)), "speedup_min": min(ratios),
        "speedup_max": max(ratios), "same_bits_one_and_two_threads": same,
        "threading_layer": numba.threading_layer()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
