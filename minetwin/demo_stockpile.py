"""A stand-alone stockpile process for demonstrating and testing the monitor.

With ``--scenario FILE`` it runs the mine simulator (``cosim.scenario``, what
``minetwin simulate`` runs) and serves its stockpile through
``surrogate.rest.RestComponent``, paced to ``--speed``. Without it, it runs
the real stockpile asset (``surrogate.stockpile.StockpileAsset``)
with its REST interface (``surrogate.rest``) in paced real time, fed by an
inbound conveyor written out here instead of the OPC UA process simulator:
one bin every ``bin_interval_s`` from two sources that alternate like the
paper's haul trucks (section "Simulator": two ore bodies of grade 0.2 and
0.8, a 55 s truck cycle, so each source delivers for half a cycle). The
feeder runs at ``discharge_rate_kg_s`` from ``discharge_start_s`` on (default
0, so that material flows through the pile from the start of a short demo;
the inflow exceeds it, so the pile grows).

Usage: ``python -m minetwin.demo_stockpile --port 0 --speed 4 [--scenario
examples/step_response.toml]`` prints ``stockpile REST on
http://127.0.0.1:PORT`` on stdout once it serves.

Parameters (``DemoFeed``)
-------------------------
bin_mass_kg : float
    Mass [kg] of each inbound bin, default 3000.
bin_interval_s : float
    Time [s] between bins, default 2 (1500 kg/s inflow).
truck_cycle_s : float
    Period [s] of the alternation between the two sources, default 55.
source_grades, source_hardness : tuple
    Grade [-] and relative hardness [-] of source 0 and 1: (0.2, 0.8), (1.0, 1.6).
discharge_start_s : float
    Time [s] the feeder starts, default 0.
discharge_rate_kg_s : float
    Feeder rate [kg/s] after the start, default 1000.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import signal
import sys
import time as wallclock
from dataclasses import dataclass

import numpy as np


@dataclass
class DemoFeed:
    """The inbound conveyor and feeder schedule of the demo (see module docstring)."""

    bin_mass_kg: float = 3000.0
    bin_interval_s: float = 2.0
    truck_cycle_s: float = 55.0
    source_grades: tuple = (0.2, 0.8)
    source_hardness: tuple = (1.0, 1.6)
    discharge_start_s: float = 0.0
    discharge_rate_kg_s: float = 1000.0

    def source_names(self) -> dict:
        """Display names of the two sources: the ore body and its grade in %."""
        return {k: f"ore body {'AB'[k]} ({100 * g:.0f} % grade)"
                for k, g in enumerate(self.source_grades)}

    def deliver(self, asset, rng, t0: float, t1: float, next_tracking_id: int) -> int:
        """Hand the asset the bins due in (t0, t1]; returns the next tracking id."""
        first = int(np.floor(t0 / self.bin_interval_s)) + 1
        last = int(np.floor(t1 / self.bin_interval_s))
        for k in range(first, last + 1):
            t_bin = k * self.bin_interval_s
            source = int((t_bin % self.truck_cycle_s) >= self.truck_cycle_s / 2)
            grade = float(np.clip(self.source_grades[source] + rng.normal(0, 0.03), 0, 1))
            asset.receive_bin(next_tracking_id, self.bin_mass_kg, grade,
                              self.source_hardness[source], source=source)
            next_tracking_id += 1
        asset.set_discharge_rate(self.discharge_rate_kg_s if t1 >= self.discharge_start_s else 0.0)
        return next_tracking_id


async def run(port: int, host: str, speed: float, dt: float, model: str, seed: int,
              duration: float) -> int:
    from surrogate.rest import start_rest
    from surrogate.stockpile import StockpileAsset

    feed = DemoFeed()
    asset = StockpileAsset(model, seed=seed, source_names=feed.source_names())
    rng = np.random.default_rng(seed)
    runner, actual = await start_rest(asset, host, port)
    print(f"stockpile REST on http://{host}:{actual}", flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    tracking_id = 1
    start = wallclock.monotonic()
    tracking_id = feed.deliver(asset, rng, -dt, 0.0, tracking_id)  # the bin at t = 0
    try:
        while not stop.is_set() and asset.time < duration:
            tracking_id = feed.deliver(asset, rng, asset.time, asset.time + dt, tracking_id)
            asset.step(dt)
            lag = start + asset.time / speed - wallclock.monotonic()
            try:
                await asyncio.wait_for(stop.wait(), timeout=max(lag, 0.0))
            except asyncio.TimeoutError:
                pass
    finally:
        await runner.cleanup()
    return 0


def run_scenario(path: str, port: int, host: str, speed: float, duration: float,
                 display_radius_m: float) -> int:
    """Run the mine simulator's scenario ``path`` and serve its stockpile."""
    from cosim.scenario import build, load
    from surrogate.rest import serve_simulation

    simulation = build(load(path), progress=False)
    rest = serve_simulation(simulation, host=host, port=port, realtime_factor=speed,
                            display_radius_m=display_radius_m)
    print(f"stockpile REST on http://{host}:{rest.port}", flush=True)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    until = duration if math.isfinite(duration) else simulation.config["simulation"]["until_s"]
    try:
        simulation.run(until)
    finally:
        simulation.close()
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m minetwin.demo_stockpile",
        description="Run a stockpile asset fed by a scheduled inbound conveyor and serve its "
                    "REST interface (for demonstrating and testing the monitor).")
    parser.add_argument("--port", type=int, default=0, help="REST port (0: a free one)")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (127.0.0.1)")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="simulated seconds per wall-clock second (1)")
    parser.add_argument("--dt", type=float, default=0.5, help="step [s] (0.5)")
    parser.add_argument("--model", default="fifo", help="storage model (fifo)")
    parser.add_argument("--seed", type=int, default=0, help="seed (0)")
    parser.add_argument("--duration", type=float, default=float("inf"),
                        help="simulated seconds to run (until stopped; with --scenario: "
                             "the scenario's until_s)")
    parser.add_argument("--scenario", help="run this mine-simulator scenario (TOML) instead")
    parser.add_argument("--display-radius", type=float, default=30.0,
                        help="schematic pile radius [m] with --scenario (30)")
    args = parser.parse_args(argv)
    if not (args.speed > 0 and args.dt > 0):
        print("demo_stockpile: error: --speed and --dt must be > 0", file=sys.stderr)
        return 2
    if args.scenario:
        return run_scenario(args.scenario, args.port, args.host, args.speed, args.duration,
                            args.display_radius)
    return asyncio.run(run(args.port, args.host, args.speed, args.dt, args.model, args.seed,
                           args.duration))


if __name__ == "__main__":
    sys.exit(main())
