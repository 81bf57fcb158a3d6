"""Batches on the executors of ``cosim.batch``: scaling of a small DEM design and
the per-task overhead, local process pool and a real Ray cluster, in one run.

* Scaling: a fixed design of ``--runs`` independent DEM runs (the reduced
  design's 300-disk base pile, built once before the timing; each run starts
  from it, the reduced design's rates) on 1 and 2 workers of each executor.
  Efficiency per worker = wall(1 worker) / (workers x wall(workers)); 1.0 is
  perfect scaling. The machine is shared: compare the ratios of one run.
* Overhead: ``--empty`` tasks that do nothing (``dict()``), wall time per task
  on each executor.
* The Ray cluster is started here on 127.0.0.1 (head + one worker node, one
  CPU each, ``ray start``) and stopped after.

    .venv/bin/python benchmarks/bench_batch.py [--runs 4] [--seconds 5] [--empty 200]

Prints one JSON object on stdout (progress on stderr); never asserts on time.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from cosim import batch
from surrogate.rom import paper_design as pd


def design_of(runs: int, seconds: float = 5.0) -> pd.Design:
    """``runs`` runs from the reduced design's base pile, ``seconds`` [s] each at the
    rates of its first run (distinct seeds, so distinct keys)."""
    reduced = pd.reduced_design()
    first = reduced.runs[0]
    return dataclasses.replace(reduced, name="bench", runs=tuple(
        dataclasses.replace(first, name=f"bench_{k}", seed=k, duration=seconds,
                            first_tracking_id=10_000 * (k + 1)) for k in range(runs)))


def timed_design(design, pile_states: Path, executor) -> float:
    work = Path(tempfile.mkdtemp(prefix="bench_batch_"))
    try:
        shutil.copytree(pile_states, work / "states")
        started = time.perf_counter()
        manifest = pd.run_design(design, work, executor=executor, progress=lambda m: None)
        wall = time.perf_counter() - started
        done = sum(r["status"] == "done" for r in manifest["runs_finished"])
        if done != len(design.runs):
            raise RuntimeError(f"{done} of {len(design.runs)} runs done")
        return wall
    finally:
        shutil.rmtree(work, ignore_errors=True)


def overhead(executor, tasks: int) -> float:
    work = [batch.Task(f"empty {k}", dict, {"k": k}) for k in range(tasks)]
    started = time.perf_counter()
    records = batch.run_batch(work, executor, progress=False)
    wall = time.perf_counter() - started
    if any(r["status"] != "done" for r in records):
        raise RuntimeError("an empty task failed")
    return wall / tasks


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=4, help="DEM runs of the design (4)")
    parser.add_argument("--seconds", type=float, default=5.0,
                        help="simulated seconds of each run [s] (5; longer runs weigh the "
                             "workers' start-up less)")
    parser.add_argument("--empty", type=int, default=200, help="empty tasks per executor (200)")
    args = parser.parse_args(argv)
    from minetwin.ray_executor import RayExecutor
    from minetwin.testing.ray_cluster import LocalRayCluster

    design = design_of(args.runs, args.seconds)
    pile = Path(tempfile.mkdtemp(prefix="bench_batch_pile_"))
    result = {"design": {"runs": args.runs, "run_duration_s": design.runs[0].duration,
                         "particles": design.piles[0].particles},
              "empty_tasks": args.empty, "scaling": {}, "overhead_s_per_task": {},
              # a shared machine: other work competes for the cores the workers need
              "load_average_1min_start": os.getloadavg()[0]}
    try:
        print("bench_batch: building the base pile", file=sys.stderr, flush=True)
        # a 1 s run of another seed builds the pile and compiles the DEM kernels in this
        # process (and numba's cache), so no 1-worker timing is charged for either
        warm = dataclasses.replace(design.runs[0], name="warm", seed=10_000, duration=1.0)
        pd.run_design(dataclasses.replace(design, runs=(warm,)), pile, workers=1,
                      progress=lambda m: None)
        with LocalRayCluster(workers=1, cpus_per_node=1) as cluster:
            makers = {"local": lambda n: batch.LocalExecutor(n),
                      "ray": lambda n: RayExecutor(cluster.address, workers=n)}
            for name, make in makers.items():
                walls = {}
                for workers in (1, 2):
                    with make(workers) as executor:
                        print(f"bench_batch: {name}, {workers} worker(s)", file=sys.stderr,
                              flush=True)
                        walls[workers] = timed_design(design, pile / "states", executor)
                result["scaling"][name] = {
                    "wall_s": {str(n): w for n, w in walls.items()},
                    "speedup_2_workers": walls[1] / walls[2],
                    "efficiency_per_worker_2": walls[1] / (2 * walls[2])}
                for workers in (1, 2):
                    with make(workers) as executor:
                        result["overhead_s_per_task"][f"{name}_{workers}"] = overhead(
                            executor, args.empty)
            import ray

            ray.shutdown()
    finally:
        shutil.rmtree(pile, ignore_errors=True)
    result["load_average_1min_end"] = os.getloadavg()[0]
    print(json.dumps(result, indent=1, allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
