"""Stable time step and throughput of the DEM on the paper-scale design pile (issue 15).

Builds the paper design's base pile (``surrogate.rom.paper_design``: 20,000
disks of 0.2-0.48 m laid out in layers and settled), then from that settled
checkpoint runs the DEM for ``--seconds`` under the hardest load of the
design (feeder at 2 t/s, inflow at 2 t/s from the 62 m inlet, so the run
holds bulk contacts, floor contacts at the opening and impacts from a 29 m
fall) at a ladder of forced steps dt = f t_c, with the blow-up guard
(``doe.instability``) checked every 0.05 s. Per step it reports whether it
blew up (and when and why), the largest overlap / diameter seen and the
largest speed of the settled bulk (disks older than ``doe.BULK_AGE``), which
grows before a blow-up. It also reports particle-steps per wall and per CPU
second of the ladder runs (one process, ``NUMBA_NUM_THREADS=1``).

Run: ``.venv/bin/python benchmarks/bench_dem_step.py --out /tmp/dem_step.json``
(about 15 minutes on one core; the settled pile is cached in ``--cache``).
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from surrogate.dem import Dem  # noqa: E402
from surrogate.dem.simulation import DemBlowUp  # noqa: E402
from surrogate.rom import doe, paper_design  # noqa: E402

CHECK_EVERY = 0.05
"""Seconds [s] between blow-up checks."""


def ladder_run(path: Path, fraction: float, seconds: float) -> dict:
    dem = Dem.load_checkpoint(path)
    t_c = dem.cfg.contact_time
    dem.set_dt(fraction * t_c, force=True)
    dem.set_discharge_rate(2000.0)
    feed = doe.LotFeed(90_000, 0)
    start_time, max_overlap, max_bulk_speed, reason = dem.time, 0.0, 0.0, None
    steps0, particle_steps = dem.steps_done, 0.0
    wall0, cpu0 = time.perf_counter(), time.process_time()
    checks_per_second = int(round(1.0 / CHECK_EVERY))
    for second in range(int(round(seconds))):
        paper_design.emit_feed(dem, feed, 2000.0, inlet=0)
        for _ in range(checks_per_second):
            steps = int(np.ceil(CHECK_EVERY / dem.dt - 1e-9))
            particle_steps += steps * dem.n
            try:
                dem.step(steps)
                reason = doe.instability(dem)
            except DemBlowUp as exc:
                reason = str(exc)
            max_overlap = max(max_overlap, dem.max_overlap_ratio())
            bulk = dem.time - dem.entry_time >= doe.BULK_AGE
            if bulk.any():
                max_bulk_speed = max(max_bulk_speed,
                                     float(np.hypot(*dem.vel[bulk].T).max()))
            if reason:
                break
        if reason:
            break
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    row = {"dt_over_tc": fraction, "dt_s": dem.dt, "stable": reason is None,
           "unstable_at_s": None if reason is None else dem.time - start_time,
           "reason": reason, "max_overlap_over_diameter": max_overlap,
           "max_bulk_speed_m_s": max_bulk_speed, "steps": dem.steps_done - steps0,
           "particles_end": dem.n, "wall_s": wall, "cpu_s": cpu,
           "particle_steps_per_wall_s": particle_steps / wall,
           "particle_steps_per_cpu_s": particle_steps / cpu}
    print(json.dumps(row), file=sys.stderr, flush=True)
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fractions", default="0.16,0.18,0.20,0.22,0.24,0.26,0.30",
                        help="steps to try, as fractions of the contact time t_c")
    parser.add_argument("--seconds", type=float, default=4.0,
                        help="simulated seconds per step (4: the inflow reaches the pile)")
    parser.add_argument("--cache", type=Path, default=Path("/tmp/minetwin_paper_base_pile.npz"))
    parser.add_argument("--out", type=Path, help="write the rows as JSON here")
    args = parser.parse_args(argv)
    design = paper_design.paper_design()
    pile = design.piles[0]
    if not args.cache.is_file():
        tic = time.perf_counter()
        dem, record = paper_design.build_pile(design, pile, progress=lambda m: print(
            m, file=sys.stderr, flush=True))
        dem.save_checkpoint(args.cache)
        print(f"built {pile.name} in {time.perf_counter() - tic:.0f} s: {json.dumps(record)}",
              file=sys.stderr)
    rows = [ladder_run(args.cache, float(f), args.seconds) for f in args.fractions.split(",")]
    text = json.dumps({"pile": pile.name, "seconds": args.seconds, "rows": rows}, indent=1,
                      allow_nan=False)
    if args.out:
        args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
