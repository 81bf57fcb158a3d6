"""OPC UA exchange load benchmark: bins/s for a while, nothing lost, the lag bounded.

Real processes on 127.0.0.1: the mock 800xA server (CV101 delivers
``--bins-per-plant-s`` bins per simulated second, default 1, by shorter bins
on the same belt; the speed-up is ``--rate`` / that, so ``--rate`` is bins per
second of wall time) and the stockpile client (FIFO) over Basic256Sha256
SignAndEncrypt. After
``--seconds`` of wall time the clock is frozen, the client drains, both stop
and the exchange is audited. Prints one JSON object per rate.

Passed only if nothing is lost or duplicated, the mass balances, and the
stockpile kept up: its lag behind the plant p99 < ``MAX_LAG_P99_S`` of plant
time, its step time p99 < the exchange cycle, and it reached the frozen
clock within ``CATCH_UP_LIMIT_S`` after the load (``caught_up``; a lag that
grows fails here instead of draining for ever, and the bins it left pending
on the server count as lost in the audit). ``--rate`` takes several
rates; the last line then says the highest rate that passed (where the lag
stops being bounded).

The lag is measured in plant time, so a polling client has a floor of about
(server tick + one exchange) x speed-up: with the default plant at 100 bins/s
(speed x100, 50 ms tick) the clock jumps 5 s per tick, and a client that
keeps up perfectly still shows a p99 of several seconds. ``lag_p50_wall_s`` /
``lag_p99_wall_s`` are the lag in wall seconds; ``--bins-per-plant-s 10``
offers the same bins/s at a tenth of the speed-up, where 2 s of plant time is
above that floor at 100 bins/s; at 1,000 bins/s ``--bins-per-plant-s 100``
(speed x10, 0.5 s of plant time per tick) is.

    .venv/bin/python benchmarks/bench_opcua.py [--rate 100 300 1000] [--seconds 60]
    .venv/bin/python benchmarks/bench_opcua.py --rate 100 300 1000 --seconds 60 --bins-per-plant-s 100
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from cosim import jsonio
from opcua_server.audit import audit
from minetwin.harness import ServerProcess, StockpileProcess, drain_and_stop, prepare_state

MAX_LAG_P99_S = 2.0
"""Largest p99 lag [s of plant time] of the stockpile behind the plant that passes."""
CATCH_UP_LIMIT_S = 60.0
"""Wall time [s] the stockpile may take to reach the frozen clock after the
load (at least the load's length); one still behind then fails (caught_up
false), its backlog left pending on the server."""
CYCLE_MS = 100.0
"""The stockpile's exchange cycle [ms of wall time] (``minetwin stockpile --cycle``)."""


def run_rate(rate: float, seconds: float, model: str, bins_per_plant_s: float = 1.0) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench_opcua_") as tmp:
        work = Path(tmp)
        state = prepare_state(work / "state")
        config = None
        if bins_per_plant_s != 1.0:  # the default belt (2 m/s), bins 2 m / K long
            config = work / "plant.toml"
            config.write_text(f"[cv101]\nbin_length_m = {2.0 / bins_per_plant_s!r}\n")
        speed = rate / bins_per_plant_s
        server = ServerProcess(work, state, speed=speed, config=config)
        client = None
        try:
            client = StockpileProcess(work, state, server.url, model=model, rest=True)
            start = time.monotonic()
            while (elapsed := time.monotonic() - start) < seconds:
                time.sleep(min(10.0, seconds - elapsed))
                print(f"bench_opcua: {rate:g} bins/s, {time.monotonic() - start:.0f} s",
                      file=sys.stderr, flush=True)
            wall = time.monotonic() - start
            ledger, summary = drain_and_stop(server, client, timeout=120,
                                             catch_up_limit=max(CATCH_UP_LIMIT_S, seconds))
        finally:
            for proc in (client, server):
                if proc is not None:
                    proc.stop()
        # why the client reconnected, if it did (its log goes with the temporary folder)
        reconnect_reasons = [line.split("connection lost ", 1)[1] for line in
                             client.log_path.read_text(errors="replace").splitlines()
                             if "connection lost " in line]
    result = audit(ledger, summary)
    result.pop("lost_examples"), result.pop("duplicated_examples")
    out = {
        "benchmark": "opcua_exchange", "rate_bins_per_s": rate,
        "bins_per_plant_s": bins_per_plant_s, "speed": speed, "load_wall_s": wall,
        "bins_per_wall_s": result["bins_in"] / (ledger["time_s"] / speed),
        **result,
        "lag_p50_s": summary["lag_p50_s"], "lag_p99_s": summary["lag_p99_s"],
        "lag_p50_wall_s": summary["lag_p50_s"] / speed, "lag_p99_wall_s": summary["lag_p99_s"] / speed,
        "max_lag_s": summary["max_lag_s"],
        "max_lag_wall_s": ledger["max_surrogate_lag_s"] / speed,
        "step_time_p99_ms": summary["step_time_p99_ms"], "exchange_cycle_ms": CYCLE_MS,
        "exchange_cycles": summary["cycles"], "reconnects": summary["reconnects"],
        "reconnect_reasons": reconnect_reasons,
        "largest_step_s": summary["largest_step_s"],
        "caught_up": (summary["time_s"] >= ledger["time_s"] - 1e-9
                      and result["pending_unacknowledged"] == 0),
    }
    out["keeps_up"] = (out["lag_p99_s"] < MAX_LAG_P99_S
                       and out["step_time_p99_ms"] < CYCLE_MS)
    out["passed"] = (out["keeps_up"] and out["caught_up"] and out["tracking_ids_lost"] == 0
                     and out["tracking_ids_duplicated"] == 0
                     and out["mass_balance_rel_error"] < 1e-9)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, nargs="+", default=[120.0],
                        help="bins per wall second offered, one run per rate (default 120)")
    parser.add_argument("--seconds", type=float, default=60.0, help="wall seconds of load")
    parser.add_argument("--model", default="fifo")
    parser.add_argument("--bins-per-plant-s", type=float, default=1.0,
                        help="bins per simulated second (default 1: the default plant)")
    args = parser.parse_args(argv)
    results = []
    for rate in sorted(args.rate):
        results.append(run_rate(rate, args.seconds, args.model, args.bins_per_plant_s))
        print(jsonio.dumps(results[-1], indent=2), flush=True)
    passed = [r["rate_bins_per_s"] for r in results if r["passed"]]
    print(jsonio.dumps({"highest_rate_with_bounded_lag_bins_per_s": max(passed) if passed else None,
                      "rates": [r["rate_bins_per_s"] for r in results],
                      "passed": all(r["passed"] for r in results)}))
    return 0 if all(r["passed"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
