"""Foundation benchmarks (issue 2): particle store, virtual sensor, event store.

Prints one JSON object. Targets: sensor over 100,000 particles < 5 ms; event
store >= 200,000 particle-rows/s into SQLite.

    .venv/bin/python benchmarks/bench_foundation.py
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from cosim import sizes
from cosim.events import EventStore
from cosim.particles import ParticleStore
from cosim.sensors import Box, observe


def best_of(repeats, fn):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def bench_store(n=1_000_000):
    f = sizes.swebrec()
    store = ParticleStore()
    start = time.perf_counter()
    ids = store.add(mass=np.full(n, 100.0), f=f, grade=0.5, hardness=1.0)
    add_s = time.perf_counter() - start
    rng = np.random.default_rng(0)
    order = rng.permutation(ids)
    start = time.perf_counter()
    for chunk in np.array_split(order, 100):
        store.remove(chunk)
    remove_s = time.perf_counter() - start
    return {"particles": n, "add_s": add_s, "remove_s": remove_s,
            "add_per_particle_us": add_s / n * 1e6, "remove_per_particle_us": remove_s / n * 1e6}


def bench_sensor(n=100_000):
    rng = np.random.default_rng(0)
    store = ParticleStore(capacity=n)
    store.add(mass=rng.uniform(10, 150, n), f=sizes.swebrec(), grade=rng.random(n),
              hardness=1 + rng.random(n), position=rng.uniform(0, 60, (n, 3)),
              owner=rng.integers(0, 4, n))
    box = Box((10, 10, 10), (40, 40, 40))
    observe(store, "grade", box=box)  # compile
    return {"particles": n,
            "box_grade_ms": best_of(20, lambda: observe(store, "grade", box=box)) * 1e3,
            "owner_grade_ms": best_of(20, lambda: observe(store, "grade", owner=2)) * 1e3,
            "box_size_distribution_ms": best_of(20, lambda: observe(store, "f", box=box)) * 1e3}


def bench_events(n_events=200, per_event=1000):
    rng = np.random.default_rng(0)
    store = ParticleStore()
    store.add(mass=rng.uniform(10, 150, per_event), f=sizes.swebrec(), grade=0.5,
              hardness=1.0)
    with tempfile.TemporaryDirectory() as tmp:
        events = EventStore(Path(tmp) / "events.sqlite")
        start = time.perf_counter()
        for k in range(n_events):
            events.record("pass", "jaw", float(k), store)
        events.flush()
        elapsed = time.perf_counter() - start
        events.close()
    rows = n_events * per_event
    return {"particle_rows": rows, "wall_s": elapsed, "rows_per_s": rows / elapsed}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=1_000_000)
    args = parser.parse_args(argv)
    result = {"store": bench_store(args.particles), "sensor": bench_sensor(),
              "event_store": bench_events()}
    json.dump(result, sys.stdout, indent=2)
    print()
    return result


if __name__ == "__main__":
    main()
